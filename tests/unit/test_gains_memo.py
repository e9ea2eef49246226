"""The fusion centre's gains and decision memos (:class:`covnet.covariance_control.centre.
GainsMemo`, :class:`~covnet.covariance_control.centre.DecisionMemo`): the same bits as
computing every scan afresh, and computed once a steady state repeats them."""

import numpy as np
import pytest
import yaml

from covnet import kinds
from covnet.covariance_control.centre import DecisionMemo, Gains, GainsMemo
from covnet.covariance_control.model import build_model, decide, predict_cov
from covnet.covariance_control.network_sizes import bench_config
from tests.conftest import PAPER


def _model(tmp_path, n):
    _, paper = kinds.load(PAPER)
    path = tmp_path / "net.yaml"
    path.write_text(yaml.safe_dump(bench_config(paper, n, 200)))
    return build_model(kinds.load(path)[1])


@pytest.mark.parametrize("n", [8, 64])
def test_the_memo_gives_every_scans_gains_bit_for_bit(tmp_path, n):
    """200 scans of the covariance recursion with every sensor on (the bench network), and a
    subset changing at scans 150-160: the memo's gains and ``P⁺`` are those computed afresh,
    byte for byte; once ``P⁻`` repeats (a steady state reached bit for bit) they are the
    remembered objects, and the remembered arrays cannot be written."""
    model = _model(tmp_path, n)
    memo = GainsMemo(model)
    every = tuple(range(n))
    P_memo = P_plain = predict_cov(model, np.asarray(model.P0))
    reused = 0
    seen: set[int] = set()
    for k in range(1, 201):
        subset = every[: n // 2] if 150 <= k <= 160 else every
        g = memo.of(P_memo, subset)
        plain = Gains.of(model, P_plain, subset)
        assert g.subset == plain.subset and g.R == plain.R
        assert g.P_post.tobytes() == plain.P_post.tobytes(), k
        assert all(a.tobytes() == b.tobytes() for a, b in zip(g.K, plain.K, strict=True)), k
        reused += id(g) in seen
        seen.add(id(g))
        P_memo, P_plain = predict_cov(model, g.P_post), predict_cov(model, plain.P_post)
    assert reused > 50  # the steady state came well before scan 150 and again after 160
    with pytest.raises(ValueError, match="read-only"):
        g.P_post[0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        g.K[0][0, 0] = 1.0


def test_the_memo_keeps_its_size():
    model = type("M", (), {"H": np.hstack([np.eye(2), np.zeros((2, 2))]),
                           "R": [np.eye(2)]})()  # fmt: skip
    memo = GainsMemo(model)
    for i in range(GainsMemo.SIZE + 5):
        memo.of(np.eye(4) * (1.0 + i), (0,))
    assert len(memo._memo.items) == GainsMemo.SIZE


def _same(a, b):
    return (a.subset, a.value, a.P.tobytes(), a.n_feasible, a.n_evaluated, a.lower_bound,
            a.gap) == (b.subset, b.value, b.P.tobytes(), b.n_feasible, b.n_evaluated,
                       b.lower_bound, b.gap)  # fmt: skip


@pytest.mark.parametrize("metric", ["spectral", "abs_trace", "svd"])
def test_the_decision_memo_decides_every_scan_bit_for_bit(paper, metric):
    """The paper scenario's 100 scans (the exact search over 8 sensors, the desired schedule
    changing at scan 51, a failed sensor at scans 30-40): every decision of the memo is the one
    made afresh, field for field; the steady state's are remembered ones."""
    model = build_model(paper)
    memo = DecisionMemo(model)
    assert memo.on
    P = predict_cov(model, np.asarray(model.P0))
    reused, seen = 0, set()
    for k in range(1, model.scans + 1):
        unavailable = frozenset({2}) if 30 <= k <= 40 else frozenset()
        got = memo.decide(P, k, metric, unavailable)
        assert _same(got, decide(model, P, k, metric, unavailable)), k
        reused += id(got) in seen
        seen.add(id(got))
        P = predict_cov(model, Gains.of(model, P, got.subset).P_post)
    assert reused > 0
    with pytest.raises(ValueError, match="read-only"):
        got.P[0, 0] = 1.0


def test_decisions_that_depend_on_more_are_not_remembered(paper):
    """A search stopped by the clock, or a baseline policy, decides afresh every time."""
    from covnet.covariance_control.config import normalised, with_overrides

    for allocation in ({"time_limit_s": 1.0, "search": "bounded"}, {"policy": "round_robin",
                                                                     "budget": 2}):  # fmt: skip
        sc = with_overrides(paper, allocation={**normalised(paper)["allocation"], **allocation})
        model = build_model(sc)
        memo = DecisionMemo(model)
        assert not memo.on
        P = predict_cov(model, np.asarray(model.P0))
        a, b = memo.decide(P, 5, "spectral", frozenset()), memo.decide(P, 5, "spectral",
                                                                         frozenset())  # fmt: skip
        assert a is not b
