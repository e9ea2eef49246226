"""The in-process mobile run: the whole scan loop for one seed and one solver, no bus.

Per scan ``k = 1..K`` (the steps of :mod:`covnet.mobile.model`)::

    predict every track to k
    cost tensor (M, N, 9), decision (the configured solver; the exact one too if compare_exact)
    platforms move by their modes
    each chosen pair draws detection and noise from [seed, 3, k, i, j] with the true geometry
    each track updates with its detection (Joseph form) or keeps its prediction

Everything but the wall times is a function of the config and the seed: the same seed gives
identical arrays in any process.  The LP and MILP runs share random numbers wherever they make
the same decisions.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np

from covnet.core.mobile.decision import compare, decide_milp, relaxation
from covnet.core.mobile.models import predict_tracks, usage_cost
from covnet.mobile.config import MobileConfig
from covnet.mobile.model import (
    build_model,
    decide,
    initial_tracks,
    lp_reference,
    measure_pair,
    move_platforms,
    truth,
    update_track,
)

#: arrays of a run that hold wall-clock times (everything else is deterministic)
TIMING_FIELDS = ("cost_s", "solve_s", "compare_s")


@dataclass(frozen=True)
class MobileRun:
    """Per-scan arrays of one run.  Rows of the ``(K + 1, ...)`` arrays are scans 0..K (row 0 is
    the start); rows of the ``(K, ...)`` arrays are scans 1..K.  Comparison arrays are NaN (and
    conflicts -1) unless the exact solver was also run."""

    solver: str
    seed: int
    truth: np.ndarray  # (K+1, M, 4)
    x_est: np.ndarray  # (K+1, M, 4) posterior means (row 0: initial estimate)
    P_post: np.ndarray  # (K+1, M, 4, 4)
    platforms: np.ndarray  # (K+1, N, 2) positions
    modes: np.ndarray  # (K, N) int
    assign: np.ndarray  # (K, M) int, sensor index or -1 (unobserved)
    detected: np.ndarray  # (K, M) bool
    pd_true: np.ndarray  # (K, M) Pd of the chosen pair from the truth geometry (NaN: none)
    usage: np.ndarray  # (K,) Σ b_jρ over the chosen pairs
    objective: np.ndarray  # (K,) J of the decision made
    status: np.ndarray  # (K,) solver status
    fractional: np.ndarray  # (K,) LP vertex rounded
    J_lp: np.ndarray  # (K,) LP optimum before the post-step (when known)
    J_post: np.ndarray  # (K,) J_LP+post
    J_star: np.ndarray  # (K,) MILP optimum
    J_relax: np.ndarray  # (K,) LP relaxation of the exact problem
    gap: np.ndarray  # (K,) (J_LP+post − J*) / |J*|
    conflicts: np.ndarray  # (K,) mode conflicts resolved by the post-step
    mip_gap: np.ndarray  # (K,) HiGHS's gap of the exact solve
    exact_status: np.ndarray  # (K,) HiGHS status of the exact solve (-1: not run)
    cost_s: np.ndarray  # (K,) wall time of the cost tensor
    solve_s: np.ndarray  # (K,) wall time of the configured solver
    compare_s: np.ndarray  # (K,) wall time of the comparison: the other solver + the relaxation

    def arrays(self) -> dict[str, np.ndarray]:
        """Every array field by name."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("solver",)}


Progress = Callable[[int, int], None]


def run(
    cfg: MobileConfig, solver: str | None = None, progress: Progress | None = None
) -> MobileRun:
    """Run ``cfg`` (its seed) with ``solver`` (default: the config's)."""
    model = build_model(cfg)
    solver = solver or model.solver
    K, M, N = model.scans, model.M, model.N
    X = truth(model)
    x, P = initial_tracks(model)
    pos = model.sensors.position.copy()
    b = usage_cost(model.sensors.b0, model.sensors.b1)  # (N, 9)

    x_est = np.empty((K + 1, M, 4))
    P_post = np.empty((K + 1, M, 4, 4))
    platforms = np.empty((K + 1, N, 2))
    x_est[0], P_post[0], platforms[0] = x, P, pos
    modes = np.empty((K, N), dtype=np.int64)
    assign = np.empty((K, M), dtype=np.int64)
    detected = np.zeros((K, M), dtype=bool)
    pd_true = np.full((K, M), np.nan)
    usage = np.zeros(K)
    J = np.empty(K)
    status = np.empty(K, dtype=np.int64)
    fractional = np.zeros(K, dtype=bool)
    J_lp, J_post, J_star, J_relax, gap, mip_gap = (np.full(K, np.nan) for _ in range(6))
    conflicts = np.full(K, -1, dtype=np.int64)
    exact_status = np.full(K, -1, dtype=np.int64)
    cost_s, solve_s, compare_s = np.zeros(K), np.zeros(K), np.zeros(K)

    for r in range(K):
        k = r + 1
        xp, Pp = predict_tracks(x, P, model.targets)
        step = decide(model, xp, Pp, pos, solver=solver)
        d = step.decision
        cost_s[r], solve_s[r] = step.cost_s, step.solve_s
        modes[r], assign[r] = d.modes, d.assign
        J[r], status[r], fractional[r] = d.objective, d.status, d.fractional
        J_lp[r] = d.J_lp
        if d.solver != "milp":
            conflicts[r], J_post[r] = d.conflicts, d.objective
        else:  # HiGHS's own gap (a time-out's is not 0), with or without the comparison
            mip_gap[r] = d.mip_gap
        if model.compare_exact:
            t0 = time.perf_counter()
            ref = lp_reference(step.problem, step)
            exact = d if d.solver == "milp" else decide_milp(step.problem, model.options)
            _, _, jr = relaxation(step.problem, model.options.linking)
            compare_s[r] = time.perf_counter() - t0
            cmp = compare(ref, exact, jr)
            J_lp[r], J_post[r], J_star[r], J_relax[r] = cmp.J_lp, cmp.J_post, cmp.J_star, jr
            gap[r], conflicts[r], mip_gap[r] = cmp.gap, cmp.conflicts, cmp.mip_gap
            exact_status[r] = cmp.exact_status

        pos, qdot = move_platforms(model, pos, d.modes)
        platforms[k] = pos
        xn, Pn = xp.copy(), Pp.copy()
        for i in np.flatnonzero(d.assign >= 0):
            j = int(d.assign[i])
            usage[r] += b[j, d.modes[j]]
            hit, z, Pd = measure_pair(model, k, int(i), j, X[k, i], pos[j], qdot[j])
            pd_true[r, i] = Pd
            if hit:
                post = update_track(model, xp[i], Pp[i], z, j, pos[j], qdot[j])
                xn[i], Pn[i] = post.x, post.P
                detected[r, i] = True
        x, P = xn, Pn
        x_est[k], P_post[k] = x, P
        if progress is not None:
            progress(k, K)

    return MobileRun(
        solver=solver,
        seed=model.seed,
        truth=X,
        x_est=x_est,
        P_post=P_post,
        platforms=platforms,
        modes=modes,
        assign=assign,
        detected=detected,
        pd_true=pd_true,
        usage=usage,
        objective=J,
        status=status,
        fractional=fractional,
        J_lp=J_lp,
        J_post=J_post,
        J_star=J_star,
        J_relax=J_relax,
        gap=gap,
        conflicts=conflicts,
        mip_gap=mip_gap,
        exact_status=exact_status,
        cost_s=cost_s,
        solve_s=solve_s,
        compare_s=compare_s,
    )
