"""Properties of the link model (covnet.core.delay) for arbitrary specs, send times and seeds."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from covnet.core.delay import DelayDist, LinkSpec, LinkState, link_stream, schedule

seconds = st.floats(0.0, 0.5, allow_nan=False)
probability = st.floats(0.0, 0.95, allow_nan=False)

dists = st.one_of(
    st.builds(lambda v: DelayDist("constant", value_s=v), seconds),
    st.builds(
        lambda a, b: DelayDist("uniform", low_s=min(a, b), high_s=max(a, b)), seconds, seconds
    ),
    st.builds(lambda m, s: DelayDist("normal", mean_s=m, std_s=s), seconds, seconds),
    st.builds(lambda m, o: DelayDist("exponential", mean_s=m, offset_s=o), seconds, seconds),
    st.builds(
        lambda xs: DelayDist("empirical", samples_s=tuple(xs)),
        st.lists(seconds, min_size=1, max_size=5),
    ),
)
links = st.builds(
    LinkSpec,
    delay=dists,
    jitter_s=st.floats(0.0, 0.1),
    loss=probability,
    reorder=st.floats(0.0, 1.0),
)


@st.composite
def send_times(draw) -> np.ndarray:
    gaps = draw(st.lists(st.floats(0.0, 0.05), min_size=0, max_size=700))
    return draw(st.floats(0.0, 100.0)) + np.cumsum(gaps)


def _with(link: LinkSpec, **kw) -> LinkSpec:
    return LinkSpec(**{**link.__dict__, **kw})


@given(links, send_times(), st.integers(0, 2**32))
def test_batch_equals_incremental(link, send, seed):
    batch = schedule(link, send, link_stream(seed, 0, 0))
    state = LinkState(link, link_stream(seed, 0, 0))
    inc = np.array([np.nan if (t := state.on_send(s)) is None else t for s in send])
    np.testing.assert_array_equal(batch.deliver_at, inc)


@given(links, send_times(), st.integers(0, 2**32))
def test_never_early_and_nan_exactly_where_lost(link, send, seed):
    s = schedule(link, send, link_stream(seed, 1, 0))
    assert np.array_equal(np.isnan(s.deliver_at), s.lost)
    assert np.all(s.deliver_at[~s.lost] >= send[~s.lost])
    if link.loss == 0:
        assert not s.lost.any()


@given(links, send_times(), st.integers(0, 2**32))
def test_fifo_without_reorder(link, send, seed):
    s = schedule(_with(link, reorder=0.0), send, link_stream(seed, 0, 1))
    assert np.all(np.diff(s.deliver_at[~s.lost]) >= 0)


@given(links, send_times(), st.integers(0, 2**32))
def test_each_packet_is_either_fifo_or_on_its_own_delay(link, send, seed):
    """Loss and delays do not depend on ``reorder``, so every delivery equals the FIFO one
    (``reorder = 0``) or the independent one (``reorder = 1``), and lies between them."""
    fifo = schedule(_with(link, reorder=0.0), send, link_stream(seed, 2, 0)).deliver_at
    own = schedule(_with(link, reorder=1.0), send, link_stream(seed, 2, 0)).deliver_at
    got = schedule(link, send, link_stream(seed, 2, 0)).deliver_at
    kept = ~np.isnan(got)
    assert np.array_equal(kept, ~np.isnan(fifo))
    assert np.all((got[kept] == fifo[kept]) | (got[kept] == own[kept]))
    assert np.all((own[kept] <= got[kept]) & (got[kept] <= fifo[kept]))


@given(links, st.floats(0.0, 0.95), send_times(), st.integers(0, 2**32))
def test_more_loss_loses_a_superset(link, other, send, seed):
    lo, hi = sorted((link.loss, other))
    a = schedule(_with(link, loss=lo), send, link_stream(seed, 3, 0))
    b = schedule(_with(link, loss=hi), send, link_stream(seed, 3, 0))
    assert np.all(b.lost[a.lost])
    # a survivor's own delay is unchanged; fewer packets ahead of it can only shorten its wait
    kept = ~b.lost
    assert np.all(b.deliver_at[kept] <= a.deliver_at[kept])
    own = [
        schedule(_with(link, loss=p, reorder=1.0), send, link_stream(seed, 3, 0)) for p in (lo, hi)
    ]
    np.testing.assert_array_equal(own[0].deliver_at[kept], own[1].deliver_at[kept])


@given(dists, st.integers(0, 300), st.integers(0, 2**32))
def test_samples_are_finite_and_non_negative(dist, n, seed):
    x = dist.sample(link_stream(seed, 0, 0), n)
    assert x.shape == (n,)
    assert np.all(np.isfinite(x) & (x >= 0))
    assert dist.mean() >= 0 and dist.var() >= 0
    assert DelayDist.from_dict(dist.to_dict()) == dist
