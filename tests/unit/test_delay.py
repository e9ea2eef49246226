"""Link models (covnet.core.delay): distributions against their formulas, loss, FIFO and
reordering, batch == incremental, validation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covnet.core.delay import (
    BLOCK,
    DelayDist,
    LinkSpec,
    LinkState,
    link_stream,
    schedule,
)
from covnet.core.streams import sensor_stream

N = 200_000


def _rng(k: int = 0) -> np.random.Generator:
    return link_stream(2026, k, 0)


def _incremental(link: LinkSpec, send: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    state = LinkState(link, rng)
    out = [state.on_send(t) for t in send]
    return np.array([np.nan if t is None else t for t in out])


@pytest.mark.parametrize(
    ("dist", "mean", "var"),
    [
        (DelayDist("constant", value_s=0.02), 0.02, 0.0),
        (DelayDist("uniform", low_s=0.005, high_s=0.025), 0.015, 0.02**2 / 12),
        (DelayDist("normal", mean_s=0.03, std_s=0.004), 0.03, 0.004**2),
        (DelayDist("exponential", mean_s=0.01, offset_s=0.002), 0.012, 0.01**2),
        (DelayDist("empirical", samples_s=(0.01, 0.02, 0.06)), 0.03, np.var([0.01, 0.02, 0.06])),
    ],
    ids=lambda v: v.kind if isinstance(v, DelayDist) else "",
)
def test_sample_moments_match_the_formulas(dist: DelayDist, mean: float, var: float):
    x = dist.sample(_rng(), N)
    assert x.shape == (N,) and np.all(x >= 0)
    assert dist.mean() == pytest.approx(mean, rel=1e-12)
    assert dist.var() == pytest.approx(var, rel=1e-12, abs=1e-18)
    # 6 standard errors of the mean; the variance to 3 %
    assert abs(x.mean() - mean) <= 6 * math.sqrt(var / N) + 1e-15
    assert x.var() == pytest.approx(var, rel=0.03, abs=1e-15)


def test_normal_is_clipped_at_zero_and_its_mean_is_the_clipped_mean():
    d = DelayDist("normal", mean_s=0.001, std_s=0.002)
    x = d.sample(_rng(), N)
    assert x.min() == 0.0
    assert np.mean(x == 0.0) == pytest.approx(0.5 * math.erfc(0.5 / math.sqrt(2)), abs=0.005)
    # E[max(X, 0)] > mu, and the closed form agrees with the sample
    assert d.mean() > 0.001
    assert x.mean() == pytest.approx(d.mean(), rel=0.01)
    assert x.var() == pytest.approx(d.var(), rel=0.03)


def test_jitter_is_clipped_at_zero():
    link = LinkSpec(DelayDist("constant", value_s=0.001), jitter_s=0.01, reorder=1.0)
    s = schedule(link, np.zeros(5000), _rng())
    assert np.all(s.deliver_at >= 0.0)
    assert np.mean(s.deliver_at == 0.0) > 0.4  # P(N(1ms, 10ms) < 0) = 0.46


def test_jitter_adds_its_variance():
    link = LinkSpec(DelayDist("uniform", low_s=0.1, high_s=0.2), jitter_s=0.01, reorder=1.0)
    s = schedule(link, np.zeros(N), _rng())
    assert s.deliver_at.var() == pytest.approx(0.1**2 / 12 + 0.01**2, rel=0.03)


def test_loss_fraction_is_binomial_and_reproducible():
    p, n = 0.3, 20_000
    link = LinkSpec(DelayDist("constant", value_s=0.01), loss=p)
    send = np.arange(n) * 1e-3
    a = schedule(link, send, link_stream(7, 3, 1))
    b = schedule(link, send, link_stream(7, 3, 1))
    assert abs(a.lost.mean() - p) <= 5 * math.sqrt(p * (1 - p) / n)
    np.testing.assert_array_equal(a.lost, b.lost)
    np.testing.assert_array_equal(a.deliver_at, b.deliver_at)
    assert np.all(np.isnan(a.deliver_at[a.lost])) and not np.any(np.isnan(a.deliver_at[~a.lost]))
    other = schedule(link, send, link_stream(7, 3, 0))
    assert not np.array_equal(a.lost, other.lost)


def test_more_loss_loses_a_superset_and_keeps_the_delays():
    send = np.arange(3000) * 1e-3
    dist = DelayDist("exponential", mean_s=0.002)
    lo = schedule(LinkSpec(dist, loss=0.1, reorder=1.0), send, _rng())
    hi = schedule(LinkSpec(dist, loss=0.4, reorder=1.0), send, _rng())
    assert np.all(hi.lost[lo.lost])
    both = ~hi.lost
    np.testing.assert_array_equal(lo.deliver_at[both], hi.deliver_at[both])


def test_fifo_when_reorder_is_zero():
    link = LinkSpec(DelayDist("exponential", mean_s=0.02), jitter_s=0.005, loss=0.2)
    send = np.cumsum(_rng(1).exponential(0.002, 5000))
    s = schedule(link, send, _rng())
    t = s.deliver_at[~s.lost]
    assert np.all(np.diff(t) >= 0)
    assert np.all(t >= send[~s.lost])


def test_reorder_produces_overtakes_and_only_reordered_packets_overtake():
    dist = DelayDist("uniform", low_s=0.0, high_s=0.05)
    send = np.arange(2000) * 1e-3
    full = schedule(LinkSpec(dist, reorder=1.0), send, _rng())
    # reorder = 1: every packet keeps its own delay
    d = full.deliver_at - send
    assert np.all((d >= 0) & (d <= 0.05))
    assert np.sum(np.diff(full.deliver_at) < 0) > 100
    part = schedule(LinkSpec(dist, reorder=0.1), send, _rng())
    t = part.deliver_at
    overtakers = [i for i in range(1, len(t)) if t[i] < np.max(t[:i])]
    assert overtakers
    # a packet that overtakes is delivered exactly at its own delay (it was chosen to reorder)
    assert all(t[i] == full.deliver_at[i] for i in overtakers)
    assert len(overtakers) < 0.2 * len(t)


@pytest.mark.parametrize("n", [0, 1, BLOCK - 1, BLOCK, BLOCK + 1, 3 * BLOCK + 17])
@pytest.mark.parametrize(
    "link",
    [
        LinkSpec(),
        LinkSpec(DelayDist("normal", mean_s=0.01, std_s=0.01), jitter_s=0.002, loss=0.3),
        LinkSpec(DelayDist("empirical", samples_s=(0.0, 0.01, 0.1)), loss=0.1, reorder=0.3),
    ],
)
def test_batch_equals_incremental(link: LinkSpec, n: int):
    send = np.cumsum(_rng(5).exponential(0.003, n))
    batch = schedule(link, send, _rng())
    inc = _incremental(link, send, _rng())
    np.testing.assert_array_equal(batch.deliver_at, inc)
    np.testing.assert_array_equal(batch.lost, np.isnan(inc))


def test_ideal_link_changes_nothing():
    assert LinkSpec().is_ideal
    assert LinkSpec(DelayDist("normal", mean_s=0.0, std_s=0.0), reorder=0.5).is_ideal
    assert not LinkSpec(DelayDist("normal", mean_s=0.0, std_s=1e-3)).is_ideal
    assert not LinkSpec(jitter_s=1e-3).is_ideal
    assert not LinkSpec(loss=0.01).is_ideal
    send = np.sort(_rng(2).uniform(0, 1, 1000))
    s = schedule(LinkSpec(), send, _rng())
    np.testing.assert_array_equal(s.deliver_at, send)


def test_link_stream_is_its_own_domain():
    a = link_stream(1, 0, 0).random(4)
    np.testing.assert_array_equal(a, link_stream(1, 0, 0).random(4))
    assert not np.array_equal(a, link_stream(1, 0, 1).random(4))
    assert not np.array_equal(a, link_stream(1, 1, 0).random(4))
    assert not np.array_equal(a, sensor_stream(1, 0, 0).random(4))
    with pytest.raises(ValueError, match="link_index"):
        link_stream(1, -1, 0)


def test_round_trip_through_dicts():
    link = LinkSpec(DelayDist("empirical", samples_s=[0.1, 0.2]), jitter_s=0.01, loss=0.1)
    assert LinkSpec.from_dict(link.to_dict()) == link
    assert LinkSpec.from_dict({"loss": 0.2}) == LinkSpec(loss=0.2)
    assert link.delay.samples_s == (0.1, 0.2)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: DelayDist("constant", value_s=-0.001), r"value_s must be finite and >= 0"),
        (lambda: DelayDist("normal", mean_s=-0.01, std_s=0.1), r"mean_s must be .*>= 0"),
        (lambda: DelayDist("normal", mean_s=0.01, std_s=-1.0), r"std_s must be .*>= 0"),
        (lambda: DelayDist("uniform", low_s=0.2, high_s=0.1), r"low_s must be <= high_s"),
        (lambda: DelayDist("exponential", mean_s=math.inf), r"mean_s must be finite"),
        (lambda: DelayDist("empirical"), r"samples_s must hold at least one"),
        (lambda: DelayDist("empirical", samples_s=(0.1, -0.1)), r"samples_s must be .*>= 0"),
        (lambda: DelayDist("gamma"), r"kind must be one of constant, uniform"),
        (lambda: DelayDist("constant", std_s=0.1), r"std_s is not a parameter of kind"),
        (lambda: LinkSpec(loss=1.0), r"loss must be in \[0, 1\)"),
        (lambda: LinkSpec(loss=-0.1), r"loss must be in \[0, 1\)"),
        (lambda: LinkSpec(loss=math.nan), r"loss must be in \[0, 1\)"),
        (lambda: LinkSpec(reorder=1.5), r"reorder must be in \[0, 1\]"),
        (lambda: LinkSpec(jitter_s=-1e-3), r"jitter_s must be finite and >= 0"),
        (lambda: LinkSpec(delay=0.01), r"delay must be a DelayDist"),  # type: ignore[arg-type]
        (lambda: LinkSpec.from_dict({"latency": 1}), r"no field 'latency'"),
        (lambda: LinkSpec.from_dict({"delay": {"value_s": 0.1}}), r"kind is required: one of"),
        (lambda: schedule(LinkSpec(), np.array([1.0, 0.5]), _rng()), r"non-decreasing"),
        (lambda: schedule(LinkSpec(), np.array([np.nan]), _rng()), r"finite"),
        (lambda: LinkState(LinkSpec(), _rng()).on_send(math.inf), r"t_send must be finite"),
    ],
)
def test_validation_names_the_field(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_incremental_refuses_time_going_back():
    state = LinkState(LinkSpec(), _rng())
    assert state.on_send(1.0) == 1.0
    with pytest.raises(ValueError, match="previous send time"):
        state.on_send(0.5)
