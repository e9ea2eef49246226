"""Exact branch and bound on problems full of exact and near ties: duplicate sensors, sensors with
tiny gains, a zero-gain sensor, on loose and tight scans of the paper's recursion; every metric
against the exhaustive search (subset, value and ``P`` bits).  Also the reduced relaxation's
pieces that decide what is pruned: the logdet bound in ``Z`` (:meth:`_Relaxation.z_convex`) is
below every completion's exact value, and the relaxation's stopping goal is the pre-image of the
threshold under the final deflation."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from test_search import paper_run  # (P_pred, P_d) at given scans of the paper's recursion

from covnet.core.allocation import search as S
from covnet.core.allocation.exact import Constraints, allocate_exhaustive
from covnet.core.metrics import METRICS
from covnet.core.sensing import correlated_noise, information_gain, position_matrix
from covnet.covariance_control.bench_allocation import PAPER_TABLE

PAPER = PAPER_TABLE  # the paper's 8 sensors (sx [m], sy [m], rho)


def _gain(j, k=1.0):
    sx, sy, rho = PAPER[j % 8]
    return information_gain(position_matrix(), correlated_noise(sx * k, sy * k, rho))


def tie_gains(kind):
    """12 sensors with many ties.  ``dup``: the paper's first six, then exact copies of 0, 2, 5,
    a zero gain and two tiny ones; ``near``: six, copies scaled by ``1 + 1e-12`` and ``1 - 1e-11``
    (values within the tie tolerance, not bit-equal), a copy, tiny ones and a zero gain;
    ``weak``: six, then six sensors of which several barely move any value."""
    G = [_gain(j) for j in range(6)]
    if kind == "dup":
        G += [G[0], G[2], G[5], np.zeros((4, 4)), G[1] * 1e-9, G[3] * 1e-13]
    elif kind == "near":
        G += [G[0] * (1 + 1e-12), G[2] * (1 - 1e-11), G[4], G[5] * 1e-10, G[1] * 1e-14]
        G += [np.zeros((4, 4))]
    else:
        G += [_gain(j, 40.0) for j in range(3)] + [_gain(j, 1e4) for j in range(3, 6)]
    return np.array(G)


@pytest.mark.parametrize("kind", ["dup", "near", "weak"])
@pytest.mark.parametrize("name", sorted(METRICS))
def test_bnb_equals_exhaustive_on_tie_heavy_problems(name, kind):
    gains = tie_gains(kind)
    problems = paper_run(gains, name, [1, 2, 5, 40, 70])
    # P_d = P_pred: measuring nothing is best (the zero-gain sensor alone, if any)
    problems.append((problems[2][0], problems[2][0]))
    for P_pred, P_d in problems:
        ref = allocate_exhaustive(P_pred, gains, P_d, name)
        got = S.allocate_bnb(P_pred, gains, P_d, name)
        assert got.status == 0
        assert (got.subset, got.value) == (ref.subset, ref.value)
        np.testing.assert_array_equal(got.P, ref.P)
        c = Constraints(frozenset({6}), frozenset({1}), 5)
        ref = allocate_exhaustive(P_pred, gains, P_d, name, c)
        got = S.allocate_bnb(P_pred, gains, P_d, name, c)
        assert (got.subset, got.value) == (ref.subset, ref.value)


def test_tie_heavy_problems_do_tie():
    """The constructions above do make ties: with duplicates, several subsets within the tie
    tolerance of the optimum (here on abs_trace at a loose scan)."""
    gains = tie_gains("dup")
    P_pred, P_d = paper_run(gains, "abs_trace", [2])[0]
    vals = []
    for size in range(1, gains.shape[0] + 1):
        for D in itertools.combinations(range(gains.shape[0]), size):
            J = np.zeros((4, 4))
            for j in D:
                J = J + gains[j]
            vals.append(float(METRICS["abs_trace"](S.spd_inverse(S.spd_inverse(P_pred) + J), P_d)))
    v = np.array(vals)
    assert (v <= v.min() * (1 + 1e-9)).sum() >= 4


def _exact(prob, D, f):
    J = np.zeros((prob.n, prob.n))
    for j in D:
        J = J + prob.G[j]
    return float(f(S.spd_inverse(prob.Y0 + J), prob.D))


def test_logdet_bound_in_Z_is_below_every_completion():
    """Nodes of paper problems (loose and tight scans) whose interval keeps logdet convex in
    ``Z``: the relaxation's bound there (iterated to the end: the tightest it gets) is <= the
    exact value of every completion; and such nodes do occur."""
    gains = np.array([_gain(j, 1.0 + 0.5 * (j // 8)) for j in range(10)])
    rng = np.random.default_rng(7)
    f = METRICS["logdet"]
    n_z = 0
    for P_pred, P_d in paper_run(gains[:8], "logdet", [1, 3, 20, 60, 90]):
        prob = S._Problem(P_pred, gains, P_d, "logdet", S.NO_CONSTRAINTS, 1e-9)
        assert prob.relax is not None
        for _ in range(12):
            depth = int(rng.integers(2, prob.m - 1))
            inc = rng.random(depth) < rng.uniform(0.1, 0.9)
            Z_lo = (prob.base + prob.S[:depth][inc].sum(axis=0))[None]
            Z_hi = Z_lo + prob.suffix[depth]
            if not prob.relax.z_convex(Z_hi)[0]:
                continue
            n_z += 1
            lb = float(prob.relax.bound(Z_lo, Z_hi, math.inf, zform=True)[0])
            fixed = [prob.free[i] for i in np.flatnonzero(inc)]
            rest = prob.free[depth:]
            values = [
                _exact(prob, sorted(fixed + list(extra)), f)
                for size in range(len(rest) + 1)
                for extra in itertools.combinations(rest, size)
                if fixed or extra
            ]
            assert lb <= min(values), (lb, min(values))
    assert n_z >= 10


@pytest.mark.parametrize("name", ["frobenius", "kl", "logdet"])
def test_relaxation_goal_is_the_pre_image_of_the_threshold(name):
    """A relaxation bound above ``_goal(tau)`` (``h``'s units) is above ``tau`` after the final
    deflation, and one a little below the goal is not: the iterations stop exactly when a node
    is pruned."""
    gains = np.array([_gain(j) for j in range(8)])
    P_pred, P_d = paper_run(gains, name, [30])[0]
    prob = S._Problem(P_pred, gains, P_d, name, S.NO_CONSTRAINTS, 1e-9)
    relax = prob.relax
    assert relax is not None
    for tau in (0.0, 1e-3, 0.5, 3.7, 250.0):
        g = relax._goal(tau)
        above = np.array([g * (1 + 1e-9) + 1e-300])
        below = np.array([g * (1 - 1e-6)])
        assert relax._final(above)[0] > tau
        assert relax._final(below)[0] <= tau
    assert relax._goal(math.inf) == math.inf


def _all_values(prob, f):
    """Exact values of every non-empty subset of the free sensors (with the required ones), by
    branching-order row."""
    rows = np.array(list(itertools.product([False, True], repeat=prob.m)))[1:]
    masks = prob.masks(rows)
    return rows, np.array([_exact(prob, list(np.flatnonzero(mk)), f) for mk in masks])


@pytest.mark.parametrize("name", ["kl", "frobenius", "logdet"])
@pytest.mark.parametrize("kind", ["paper", "dup", "near"])
def test_table_leaves_return_every_completion_below_the_threshold(kind, name):
    """The table (:class:`_Leaves`) from the root: for thresholds from the optimum to well above
    it, every subset whose exact value is <= the threshold is returned, each with a bound <= its
    exact value (the ball prunes nothing it must keep); and the ball exists on most of them."""
    gains = tie_gains(kind) if kind != "paper" else np.array([_gain(j) for j in range(11)])
    f = METRICS[name]
    balls = 0
    for P_pred, P_d in paper_run(gains, name, [1, 4, 30, 65]):
        prob = S._Problem(P_pred, gains, P_d, name, S.NO_CONSTRAINTS, 1e-9)
        leaves = S._Leaves(prob, 0)
        rows, values = _all_values(prob, f)
        f_star = float(values.min())
        for rel in (1e-9, 1e-7, 1e-5, 1e-3, 0.1):
            tau = f_star * (1.0 + rel)
            if leaves.ball(tau) is None:
                continue
            balls += 1
            packed, est, _ = leaves.leaves(
                prob.base[None], np.array([0]), np.zeros((1, (prob.m + 7) // 8), np.uint8), tau
            )
            got = {tuple(r) for r in prob.unpack(packed).tolist()}
            need = {tuple(r) for r in rows[values <= tau].tolist()}
            assert need <= got, (rel, len(need - got))
            index = {tuple(r): v for r, v in zip(rows.tolist(), values, strict=True)}
            for r, e in zip(prob.unpack(packed).tolist(), est, strict=True):
                assert e <= index[tuple(r)]
    assert balls >= 10


@pytest.mark.parametrize("name", ["kl", "frobenius", "logdet"])
@pytest.mark.parametrize("kind", ["paper", "dup", "weak"])
def test_table_below_a_tree_equals_exhaustive(kind, name, monkeypatch):
    """The table for the last few levels only (``LEAF_LEVELS`` 4: the tree above it, queries
    a few nodes at a time), with and without a budget: the exhaustive search's subset; the
    table is used."""
    used = []
    real = S._Search.leaves_expand

    def spy(self, ch):
        out = real(self, ch)
        used.append(out)
        return out

    monkeypatch.setattr(S._Search, "leaves_expand", spy)
    monkeypatch.setattr(S, "LEAF_LEVELS", 4)
    monkeypatch.setattr(S, "LEAF_GROUP", 3)
    gains = tie_gains(kind) if kind != "paper" else np.array([_gain(j) for j in range(12)])
    for P_pred, P_d in paper_run(gains, name, [1, 2, 30, 60]):
        for c in (Constraints(), Constraints(frozenset({3}), frozenset({0}), 4)):
            ref = allocate_exhaustive(P_pred, gains, P_d, name, c)
            got = S.allocate_bnb(P_pred, gains, P_d, name, c)
            assert (got.subset, got.value) == (ref.subset, ref.value)
            np.testing.assert_array_equal(got.P, ref.P)
    assert any(used)
