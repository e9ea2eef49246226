"""The assignment search's table update (``assignment_search._State.move``): several changes,
the changed columns refreshed once, give the same bits as one :meth:`_State.put` per change
(the local search's swaps, the ejection chains and the kicks rely on it), and the decisions
of the timed plan are unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.allocation import assignment_search as srch
from covnet.core.allocation.assignment import OFF, MultiConstraints, _Inputs
from covnet.covariance_control import bench_multitarget as bm


def _state(metric: str, cons: MultiConstraints) -> srch._State:
    P, J, D, w, feas = bm.problems(12, 3, metric, 2, seed=4)[1]
    cs = srch._Columns(_Inputs(P, J, D, metric, w, feas, cons, 1e-9))
    st = srch._State(cs)
    srch._forward(st)
    return st


def _tables(st: srch._State) -> tuple[bytes, ...]:
    st.fresh()
    return (st.a.tobytes(), st.v.tobytes(), st.A.tobytes(), st.R.tobytes(), st.M.tobytes())


def _random_changes(st: srch._State, rng: np.random.Generator, k: int) -> list[tuple[int, int]]:
    cs = st.cs
    out = []
    for j in rng.choice(cs.N, size=k, replace=False).tolist():
        opts = [c for c in range(cs.ncol) if cs.allow[c, j]] + [OFF]
        out.append((j, int(opts[int(rng.integers(len(opts)))])))
    return out


@pytest.mark.parametrize("metric", ["spectral", "kl", "abs_trace"])
def test_move_is_the_puts_bit_for_bit(metric: str) -> None:
    rng = np.random.default_rng(11)
    cons = MultiConstraints(required=frozenset({2}))
    st = _state(metric, cons)
    for _ in range(40):
        one, many = st.copy(), st.copy()
        changes = _random_changes(st, rng, int(rng.integers(1, 6)))
        if any(j == 2 and c == OFF for j, c in changes):
            continue  # the required sensor stays on (as every caller keeps it)
        for j, c in changes:
            one.put(j, c)
        many.move(changes)
        assert many.sets == one.sets
        assert many.stale == one.stale
        assert _tables(many) == _tables(one)
        st = many


@pytest.mark.parametrize("metric", ["spectral", "trace_diff"])
def test_swaps_with_an_off_sensor_and_chains(metric: str) -> None:
    """The local search's swap (``j`` off, ``x`` to ``j``'s column, ``j`` to ``x``'s), with
    ``x`` off, and the chain's two moves: the same tables as their puts."""
    st = _state(metric, MultiConstraints())
    on = [j for j in range(st.cs.N) if st.a[j] != OFF]
    off = [j for j in range(st.cs.N) if st.a[j] == OFF and st.cs.allow[st.a[on[0]], j]]
    assert on and off
    j, x = on[0], off[0]
    aj, ak = int(st.a[j]), int(st.a[x])
    one, many = st.copy(), st.copy()
    for jj, c in ((j, OFF), (x, aj), (j, ak)):
        one.put(jj, c)
    many.move(((j, OFF), (x, aj), (j, ak)))
    assert _tables(many) == _tables(one)
    assert many.a[j] == OFF and many.a[x] == aj
    other = next(c for c in range(st.cs.T) if c != aj and st.cs.allow[c, j])
    one, many = st.copy(), st.copy()
    one.put(j, other)
    one.put(x, aj)
    many.move(((j, other), (x, aj)))
    assert _tables(many) == _tables(one)
