"""A decision with one feasible subset (every allowed sensor required, as in ``covnet bench up
--sensors N``): ``bounded`` returns what the full bounded search returns (the same subset,
value and ``P`` bits, the value as its certified lower bound, gap 0) without solving the
root relaxation first; the exact search builds no tie rule for it (nothing to branch on)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from covnet import kinds
from covnet.core.allocation import Constraints
from covnet.core.allocation.search import _Search, allocate_bnb
from covnet.core.allocation.search_problem import _Problem
from covnet.covariance_control.model import build_model, predict_cov
from covnet.covariance_control.network_sizes import bench_config
from covnet.covariance_control.searches import SEARCHES, feasible_count

PAPER = Path(__file__).resolve().parents[2] / "configs" / "paper.yaml"


def _bench(tmp_path, n):
    """The bench network of ``n`` sensors (``covnet bench up --sensors n``): its scenario and
    model (every sensor required)."""
    import yaml

    _, sc = kinds.load(PAPER)
    path = tmp_path / "net.yaml"
    path.write_text(yaml.safe_dump(bench_config(sc, n, 20), sort_keys=False))
    _, sc_n = kinds.load(path)
    return sc_n, build_model(sc_n)


@pytest.mark.parametrize(("n", "failed"), [(30, ()), (40, (3, 17))])
def test_one_feasible_subset_is_the_bounded_search_result(tmp_path, n, failed):
    sc_n, model = _bench(tmp_path, n)
    c = model.constraints
    if failed:  # failed sensors leave the required set: still one subset
        c = Constraints(excluded=frozenset(failed), required=c.required - frozenset(failed))
    assert feasible_count(n, c) == 1
    metric = sc_n.allocation.metrics[0]
    gap, limit_s, nodes = model.search.bounded_options()
    P = model.P0
    for k in range(1, 4):
        P = predict_cov(model, P)
        got = SEARCHES["bounded"].decide(model, P, model.desired(k), metric, c)
        ref = allocate_bnb(
            P, model.gains, model.desired(k), metric, c, model.tie_rtol,
            rel_gap=gap, time_limit_s=limit_s, node_limit=nodes,
        )  # fmt: skip
        assert got.subset == ref.subset
        assert got.value == ref.value and np.array_equal(got.P, ref.P)
        assert got.lower_bound == ref.lower_bound == got.value
        assert got.gap == ref.gap == 0.0
        assert got.n_evaluated == ref.n_evaluated and got.n_feasible == 1
        P = got.P


@pytest.mark.parametrize(("n", "failed"), [(24, ()), (40, (0, 39))])
def test_one_feasible_subset_is_the_exact_search_result(tmp_path, n, failed):
    """``exact`` beyond the fast path (more than 18 sensors): the same subset, value, ``P``
    bits and count as :func:`allocate_bnb`'s exact search, and every metric's value."""
    sc_n, model = _bench(tmp_path, n)
    c = model.constraints
    if failed:
        c = Constraints(excluded=frozenset(failed), required=c.required - frozenset(failed))
    assert feasible_count(n, c) == 1
    P = predict_cov(model, model.P0)
    for metric in ("spectral", "abs_trace", "svd", "kl"):
        got = SEARCHES["exact"].decide(model, P, model.desired(1), metric, c)
        ref = allocate_bnb(P, model.gains, model.desired(1), metric, c, model.tie_rtol)
        assert got.subset == ref.subset and got.n_feasible == 1
        assert got.value == ref.value and np.array_equal(got.P, ref.P)
        assert got.n_evaluated == ref.n_evaluated
        # and it is that subset's own exact evaluation (the search's problem, no tree)
        prob = _Problem(P, model.gains, model.desired(1), metric, c, model.tie_rtol)
        mask = np.zeros((1, n), dtype=bool)
        mask[0, list(got.subset)] = True
        assert got.value == float(prob.exact(mask)[0])
        assert np.array_equal(got.P, prob.exact_covariances(mask)[0])


def test_not_every_sensor_required_is_left_to_the_search(tmp_path):
    """One feasible subset that is not "every allowed sensor required" (a budget of one and a
    single allowed sensor) goes to the search itself."""
    sc_n, model = _bench(tmp_path, 20)
    c = Constraints(excluded=frozenset(range(1, 20)), required=frozenset())
    assert feasible_count(20, c) == 1
    P = predict_cov(model, model.P0)
    got = SEARCHES["bounded"].decide(model, P, model.desired(1), "spectral", c)
    assert got.subset == (0,) and got.gap == 0.0


def test_no_tie_rule_without_a_free_sensor(tmp_path):
    """With every allowed sensor required the exact search has nothing to branch on: it builds
    no tie rule (which would bound the root first, 30-70 ms at N = 64, for one subset)."""
    sc_n, model = _bench(tmp_path, 24)
    P = predict_cov(model, model.P0)
    prob = _Problem(P, model.gains, model.desired(1), "spectral", model.constraints, 1e-9)
    assert prob.m == 0
    assert _Search(prob, 0.0, False, None, None, True).ties is None
    assert prob._root_bound is None  # the root was not bounded
