"""One feasible subset (every allowed sensor required, as in ``covnet bench up --sensors``'
networks): :func:`covnet.core.allocation.search.allocate_bnb` returns the search's record without
the search's set-up (``search_problem.only_subset``).  Oracle: the same call with the short-cut
switched off, field for field and bit for bit; the reference's value; the same errors."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.allocation import search as S
from covnet.core.allocation import search_problem as SP
from covnet.core.allocation.exact import Constraints, InfeasibleAllocation, allocate_exhaustive
from covnet.core.allocation.search import allocate_bnb
from covnet.core.metrics import METRICS
from covnet.core.sensing import correlated_noise, information_gain, position_matrix


def _problem(rng: np.random.Generator, N: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    H = position_matrix()
    noises = [
        correlated_noise(*rng.uniform(2.0, 40.0, 2), rng.uniform(-0.6, 0.6)) for _ in range(N)
    ]
    G = np.array([information_gain(H, R) for R in noises])
    A = rng.normal(size=(4, 4))
    P = A @ A.T + np.diag([400.0, 20.0, 400.0, 20.0])
    D = np.diag(rng.uniform(1.0, 30.0, 4))
    return P, G, D


def _full(monkeypatch: pytest.MonkeyPatch, *args: object) -> S.SearchResult:
    with monkeypatch.context() as m:
        m.setattr(S, "only_subset", lambda *a: None)
        return allocate_bnb(*args)  # type: ignore[arg-type]


def _same(a: S.SearchResult, b: S.SearchResult) -> None:
    assert a.subset == b.subset
    assert a.value.hex() == b.value.hex()
    assert a.lower_bound.hex() == b.lower_bound.hex()
    assert a.P.tobytes() == b.P.tobytes()
    assert (a.gap, a.n_nodes, a.n_evaluated, a.exact, a.status, a.message) == (
        b.gap,
        b.n_nodes,
        b.n_evaluated,
        b.exact,
        b.status,
        b.message,
    )


@pytest.mark.parametrize("metric", sorted(METRICS))
@pytest.mark.parametrize("N", [1, 5, 64])
def test_every_sensor_required_is_the_search_bit_for_bit(
    monkeypatch: pytest.MonkeyPatch, metric: str, N: int
) -> None:
    rng = np.random.default_rng(N)
    P, G, D = _problem(rng, N)
    c = Constraints(required=frozenset(range(N)))
    fast = allocate_bnb(P, G, D, metric, c, 1e-9)
    _same(fast, _full(monkeypatch, P, G, D, metric, c, 1e-9))
    assert fast.subset == tuple(range(N))
    if N <= 5:
        ref = allocate_exhaustive(P, G, D, metric, c)
        assert ref.subset == fast.subset and ref.value == fast.value


def test_excluded_sensors_stay_out(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every *allowed* sensor required: the excluded ones are not in the subset."""
    P, G, D = _problem(np.random.default_rng(7), 6)
    c = Constraints(excluded=frozenset({1, 4}), required=frozenset({0, 2, 3, 5}))
    fast = allocate_bnb(P, G, D, "spectral", c)
    assert fast.subset == (0, 2, 3, 5)
    _same(fast, _full(monkeypatch, P, G, D, "spectral", c))


def test_a_free_sensor_or_a_limit_takes_the_search() -> None:
    """One free sensor (two feasible subsets), no required sensor, a gap or a limit: no
    short-cut, the search decides."""
    P, G, D = _problem(np.random.default_rng(3), 4)
    assert SP.only_subset(P, G, D, "kl", Constraints(required=frozenset({0, 1, 2})), 1e-9) is None
    assert SP.only_subset(P, G, D, "kl", Constraints(), 1e-9) is None
    every = Constraints(required=frozenset(range(4)))
    assert SP.only_subset(P, G, D, "kl", every, 1e-9) is not None
    assert SP.only_subset(P, G, D, lambda A, B: np.zeros(A.shape[0]), every, 1e-9) is None
    calls: list[int] = []

    def spy(*a: object) -> None:
        calls.append(1)

    S_only = S.only_subset
    try:
        S.only_subset = spy  # type: ignore[assignment]
        allocate_bnb(P, G, D, "kl", every, rel_gap=0.01)
        allocate_bnb(P, G, D, "kl", every, time_limit_s=1.0)
        allocate_bnb(P, G, D, "kl", every, node_limit=10)
        assert calls == []
        allocate_bnb(P, G, D, "kl", every)
        assert calls == [1]
    finally:
        S.only_subset = S_only  # type: ignore[assignment]


def _error(call: object) -> tuple[type, str]:
    try:
        call()  # type: ignore[operator]
    except (ValueError, KeyError, InfeasibleAllocation) as exc:
        return type(exc), str(exc)
    raise AssertionError("no error")


def test_the_same_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    """Bad input: the same exception and message with and without the short-cut."""
    P, G, D = _problem(np.random.default_rng(5), 3)
    every = Constraints(required=frozenset(range(3)))
    bad_P = P.copy()
    bad_P[0, 0] = -1.0
    bad_D = D.copy()
    bad_D[1, 1] = np.nan
    cases = [
        (P, G, D, "kl", Constraints(required=frozenset(range(3)), max_active=2), 1e-9),
        (P, G, D, "no_such_metric", every, 1e-9),
        (bad_P, G, D, "kl", every, 1e-9),
        (P, G, bad_D, "spectral", every, 1e-9),
        (P, G[:, :2], D, "kl", every, 1e-9),
        (P, G, D, "kl", every, -1.0),
    ]
    for args in cases:
        fast = _error(lambda: allocate_bnb(*args))  # noqa: B023
        full = _error(lambda: _full(monkeypatch, *args))  # noqa: B023
        assert fast == full, args[3]
