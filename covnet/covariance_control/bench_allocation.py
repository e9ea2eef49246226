"""Benchmark: the fast exact allocator against a plain batched-numpy baseline.

Problems are predicted covariances ``P_pred`` at a few scans of the paper scenario run with
``n_sensors`` paper-like sensors: covariance recursion only (``P⁻ = F P Fᵀ + Q``, allocate with the
fast path, ``P = P_i`` of the chosen subset), controlled by the metric being measured.  Scans are
spread over both desired phases, from scan 5 on (at scans 1-2 distinct subsets can differ by a
relative 1e-9 in f, spec "Facts").

For every (metric, N): the fast path's median wall time per decision over problems x repeats, the
baseline's median, their ratio, the fast path's peak traced memory, and whether both chose the same
subset on every problem.  Per problem, each path is called once untimed (warm-up), then timed:
at least ``repeat`` calls and enough to last ``MIN_BLOCK_S`` (capped at ``MAX_REPEAT``), the
count fixed by the first problem's warm-up so every problem weighs the same, in ``ROUNDS``
alternating blocks (fast, baseline, fast, ...): each path warm in its own blocks, and a change in
the shared machine's load hits both paths alike, so their ratio is steadier than either time.
The fast path is timed as a running filter uses it: the gain-only work
(validation, the PSD check of the gains, the subset tables) is prepared once per (N, metric) by
:func:`covnet.core.allocation.prepare`, outside the timed call, and every decision is
``allocate(P_pred, plan, P_d, metric)``; ``plan_s`` / ``plan_mb`` report that one-off
preparation (time, traced peak).  The baseline gets the gains array, as written the plain way.
The baseline costs seconds at N=20, so there (``2**N - 1 > BASELINE_ONCE_ABOVE`` subsets) it runs
once per problem instead of ``repeat`` times.

Run: ``python -m covnet.covariance_control.bench_allocation``.
"""

from __future__ import annotations

import argparse
import functools
import math
import sys
import time
import tracemalloc
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation import AllocationPlan, allocate, prepare
from covnet.core.gaussian import Mat
from covnet.core.metrics import METRICS, svd
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.core.sensing import correlated_noise, information_gain, position_matrix

#: the paper's 8 sensors (sx [m], sy [m], rho), spec table
PAPER_TABLE: tuple[tuple[float, float, float], ...] = (
    (21.1, 8.2, 0.82),
    (20.3, 9.1, -0.74),
    (8.22, 20.3, 0.78),
    (9.23, 20.9, -0.61),
    (31.6, 18.1, -0.65),
    (19.1, 30.1, 0.74),
    (42.1, 43.1, 0.87),
    (41.4, 43.7, -0.94),
)
DEFAULT_P0: Mat = np.diag([1e4, 1e2, 1e4, 1e2])
DEFAULT_P0.flags.writeable = False
_D1 = np.diag([25.0, 1.4, 25.0, 1.4])
_D2 = np.diag([7.0, 0.8, 7.0, 0.8])
_D1.flags.writeable = False
_D2.flags.writeable = False
#: desired covariance schedule: (first scan, P_d)
DEFAULT_DESIRED: tuple[tuple[int, Mat], ...] = ((1, _D1), (51, _D2))
#: above this many subsets the baseline runs once per problem, not ``repeat`` times
BASELINE_ONCE_ABOVE = 2**18
#: a timed block (one path, one problem) lasts at least this long, up to MAX_REPEAT calls: short
#: calls (tens of microseconds at N = 8) get enough samples for a stable median
MIN_BLOCK_S = 0.04
MAX_REPEAT = 200
#: per problem, each path's timed calls are split into this many alternating blocks
ROUNDS = 4


def _fast_subset(P_pred: Mat, plan: AllocationPlan, P_d: Mat, name: str) -> tuple[int, ...]:
    return allocate(P_pred, plan, P_d, name).subset


def _timed(
    call: Callable[[], tuple[int, ...]], out: list[float] | None = None
) -> tuple[tuple[int, ...], float]:
    """``call()`` and its wall time (appended to ``out`` if given)."""
    t0 = time.perf_counter()
    result = call()
    dt = time.perf_counter() - t0
    if out is not None:
        out.append(dt)
    return result, dt


def _time_paths(
    fast: Callable[[], tuple[int, ...]],
    base: Callable[[], tuple[int, ...]],
    reps: dict[str, int],
    repeat: int,
    fast_t: list[float],
    base_t: list[float],
    base_once: bool,
) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Time both paths on one problem; returns their choices.

    One untimed warm-up call each (on the first problem it sets ``reps``, :func:`_repeats`),
    then ``ROUNDS`` rounds of a block of fast calls followed by a block of baseline calls, each
    path's ``reps`` calls split over the rounds: every path runs in its own warm blocks, and a
    change of the (shared) machine's load during the problem hits both alike.  ``base_once``:
    the baseline's single call is its timed one, no warm-up."""
    chosen, t_fast = _timed(fast)
    expected, t_base = _timed(base, base_t if base_once else None)
    if not reps["fast"]:
        reps["fast"] = _repeats(repeat, t_fast)
        reps["base"] = 0 if base_once else _repeats(repeat, t_base)
    rounds = min(ROUNDS, reps["fast"], reps["base"] or reps["fast"])
    for k in range(rounds):
        for _ in range(_share(reps["fast"], rounds, k)):
            _timed(fast, fast_t)
        for _ in range(_share(reps["base"], rounds, k)):
            _timed(base, base_t)
    return chosen, expected


def _share(total: int, parts: int, k: int) -> int:
    """Part ``k`` of ``total`` split into ``parts`` near-equal parts."""
    return total // parts + (1 if k < total % parts else 0)


def _repeats(repeat: int, t_call: float) -> int:
    """Timed calls per problem: at least ``repeat``, enough for ``MIN_BLOCK_S`` (at most
    ``MAX_REPEAT``) at ``t_call`` seconds per call."""
    return max(repeat, min(MAX_REPEAT, math.ceil(MIN_BLOCK_S / max(t_call, 1e-9))))


def paper_like_gains(base_table: Sequence[tuple[float, float, float]], n_sensors: int) -> Mat:
    """Information gains ``J_j = Hᵀ R_j⁻¹ H`` ``(n_sensors, 4, 4)`` of position sensors.

    Sensor ``j < len(base_table)`` is ``base_table[j]``; beyond, ``base_table[j % 8]`` with both
    sigmas scaled by ``1 + 0.5 (j // 8)`` and the same rho.
    """
    if n_sensors > len(base_table) and len(base_table) < 8:
        raise ValueError(f"the base table needs 8 sensors to extend it, got {len(base_table)}")
    H = position_matrix()
    out = np.empty((n_sensors, 4, 4))
    for j in range(n_sensors):
        if j < len(base_table):
            sx, sy, rho = base_table[j]
        else:
            sx, sy, rho = base_table[j % 8]
            k = 1.0 + 0.5 * (j // 8)
            sx, sy = sx * k, sy * k
        out[j] = information_gain(H, correlated_noise(sx, sy, rho))
    return out


def _tie_pick(values: NDArray[np.float64], masks: NDArray[np.bool_], tie_rtol: float) -> int:
    f_star = float(values.min())
    thr = f_star + tie_rtol * max(abs(f_star), np.finfo(np.float64).tiny)
    tied = np.flatnonzero(values <= thr)
    return int(min(tied, key=lambda i: (int(masks[i].sum()), tuple(np.flatnonzero(masks[i])))))


def plain_baseline(P_pred: Mat, gains: Mat, P_d: Mat, metric: str) -> tuple[int, ...]:
    """The allocation "written the straightforward way" in batched numpy, for comparison.

    All ``2^N - 1`` subsets as a 0/1 matrix, ``J_i`` by one matrix product, every
    ``P_i = inv(inv(P_pred) + J_i)`` by batched ``np.linalg.inv``, the metric by numpy's batched
    routines on the full matrices, argmin with the tie rule (fewest sensors, then lowest ids).
    """
    N, n = gains.shape[0], gains.shape[1]
    codes = np.arange(1, 2**N)
    masks = ((codes[:, None] >> np.arange(N)) & 1).astype(bool)
    J = (masks.astype(np.float64) @ gains.reshape(N, n * n)).reshape(-1, n, n)
    P = np.asarray(np.linalg.inv(np.linalg.inv(P_pred) + J), dtype=np.float64)
    M = P - P_d
    if metric == "spectral":
        f = np.abs(np.linalg.eigvalsh(M)).max(axis=-1)
    elif metric == "abs_trace":
        f = np.abs(np.diagonal(M, axis1=1, axis2=2)).sum(axis=-1)
    elif metric == "svd":
        f = svd(P, P_d)  # np.linalg.eigh of every P_i, with the spec's eigenvector convention
    elif metric == "frobenius":
        f = np.linalg.norm(M, "fro", axis=(1, 2))
    elif metric == "one_norm":
        f = np.linalg.norm(M, 1, axis=(1, 2))
    elif metric == "inf_norm":
        f = np.linalg.norm(M, np.inf, axis=(1, 2))
    elif metric == "trace_diff":
        f = np.abs(np.trace(P, axis1=1, axis2=2) - np.trace(P_d))
    elif metric == "logdet":
        ld_m = np.linalg.slogdet(0.5 * (P + P_d))[1]
        f = ld_m - 0.5 * np.linalg.slogdet(P)[1] - 0.5 * np.linalg.slogdet(P_d)[1]
    elif metric == "kl":
        t1 = np.trace(np.linalg.solve(P_d, P), axis1=1, axis2=2)
        t2 = np.trace(np.linalg.solve(P, np.broadcast_to(P_d, P.shape)), axis1=1, axis2=2)
        f = 0.25 * (t1 + t2 - 2 * n)
    else:
        f = METRICS[metric].fn(P, P_d)
    best = _tie_pick(np.asarray(f, dtype=np.float64), masks, 1e-9)
    return tuple(int(j) for j in np.flatnonzero(masks[best]))


def _desired(desired: Sequence[tuple[int, Mat]], scan: int) -> Mat:
    current = desired[0][1]
    for start, P_d in desired:
        if scan >= start:
            current = P_d
    return np.asarray(current, dtype=np.float64)


def problem_scans(n_problems: int, last_scan: int = 95) -> list[int]:
    """``n_problems`` scans spread evenly over 5..last_scan (both desired phases)."""
    return sorted({int(round(k)) for k in np.linspace(5, last_scan, n_problems)})


def paper_problems(
    gains: Mat,
    metric: str,
    scans: Sequence[int],
    *,
    T: float = 1.0,
    sigma_a: float = 0.5,
    P0: Mat = DEFAULT_P0,
    desired: Sequence[tuple[int, Mat]] = DEFAULT_DESIRED,
) -> list[tuple[Mat, Mat]]:
    """``(P_pred, P_d)`` at the given scans (1-based) of the covariance recursion controlled by
    ``metric``: ``P⁻ = F P Fᵀ + Q``, ``P = P_i`` of ``allocate(P⁻, gains, P_d, metric)``."""
    F = cv_transition(T)
    Q = dwna_process_noise(T, sigma_a)
    P = np.asarray(P0, dtype=np.float64)
    plan = prepare(gains)
    wanted = set(scans)
    out = []
    for scan in range(1, max(scans) + 1):
        P_pred = F @ P @ F.T + Q
        P_d = _desired(desired, scan)
        if scan in wanted:
            out.append((P_pred, P_d))
        P = allocate(P_pred, plan, P_d, metric).P
    return out


def run(
    base_table: Sequence[tuple[float, float, float]],
    n_sensors: Sequence[int] = (8, 12, 16, 20),
    metrics: Sequence[str] | None = None,
    *,
    T: float = 1.0,
    sigma_a: float = 0.5,
    P0: Mat = DEFAULT_P0,
    desired: Sequence[tuple[int, Mat]] = DEFAULT_DESIRED,
    n_problems: int = 5,
    repeat: int = 3,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Time :func:`covnet.core.allocation.allocate` against :func:`plain_baseline`.

    Rows ``{"metric", "n_sensors", "median_s", "baseline_median_s", "speedup", "peak_mb",
    "plan_s", "plan_mb", "agree"}``: medians (``time.perf_counter``) over problems x repeats of
    one decision ``allocate(P_pred, plan, P_d, metric)`` with the plan prepared once per
    (N, metric) outside the timing, after one untimed warm-up call per problem and path (the
    baseline once per problem, no warm-up, above ``BASELINE_ONCE_ABOVE`` subsets; repeats and
    alternating blocks: :func:`_time_paths`), ``peak_mb`` the largest tracemalloc peak of one
    fast call per problem, ``plan_s`` / ``plan_mb`` the time / tracemalloc peak of
    :func:`covnet.core.allocation.prepare`, ``agree`` whether both chose the same subset on
    every problem.
    """
    names = list(metrics) if metrics is not None else sorted(METRICS)
    scans = problem_scans(n_problems)
    rows: list[dict[str, object]] = []
    for N in n_sensors:
        gains = paper_like_gains(base_table, N)
        for name in names:
            problems = paper_problems(
                gains, name, scans, T=T, sigma_a=sigma_a, P0=P0, desired=desired
            )
            tracemalloc.start()
            t0 = time.perf_counter()
            plan = prepare(gains)
            plan_s = time.perf_counter() - t0
            plan_mb = tracemalloc.get_traced_memory()[1] / 2**20
            tracemalloc.stop()
            fast_t: list[float] = []
            base_t: list[float] = []
            peaks, agree = [], True
            once = 2**N - 1 > BASELINE_ONCE_ABOVE
            reps = {"fast": 0, "base": 0}  # set from the first problem's warm-up calls
            for P_pred, P_d in problems:
                fast = functools.partial(_fast_subset, P_pred, plan, P_d, name)
                base = functools.partial(plain_baseline, P_pred, gains, P_d, name)
                chosen, expected = _time_paths(fast, base, reps, repeat, fast_t, base_t, once)
                agree &= chosen == expected
                tracemalloc.start()
                allocate(P_pred, plan, P_d, name)
                peaks.append(tracemalloc.get_traced_memory()[1] / 2**20)
                tracemalloc.stop()
            med, base_med = float(np.median(fast_t)), float(np.median(base_t))
            row: dict[str, object] = {
                "metric": name,
                "n_sensors": N,
                "median_s": med,
                "baseline_median_s": base_med,
                "speedup": base_med / med,
                "peak_mb": max(peaks),
                "plan_s": plan_s,
                "plan_mb": plan_mb,
                "agree": bool(agree),
            }
            rows.append(row)
            if progress is not None:
                progress(_format_row(row))
    return rows


def _format_row(row: dict[str, object]) -> str:
    return (
        f"{row['metric']:<11} {row['n_sensors']:>3} {row['median_s']:>11.6f} "
        f"{row['baseline_median_s']:>11.6f} {row['speedup']:>8.1f} {row['peak_mb']:>8.1f} "
        f"{row['plan_s']:>9.5f} {row['plan_mb']:>8.1f} {row['agree']!s:>6}"
    )


def main(argv: Sequence[str] | None = None) -> int:

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sensors", type=int, nargs="+", default=[8, 12, 16, 20])
    parser.add_argument("--metrics", nargs="+", default=None, choices=sorted(METRICS))
    parser.add_argument("--problems", type=int, default=5)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    header = (
        f"{'metric':<11} {'N':>3} {'median_s':>11} {'baseline_s':>11} {'speedup':>8} "
        f"{'peak_mb':>8} {'plan_s':>9} {'plan_mb':>8} {'agree':>6}"
    )
    print(
        "per-decision time of allocate(P_pred, plan, P_d, metric), plan = prepare(gains) built "
        "once per (N, metric) outside the timing (plan_s, plan_mb: that one-off preparation)",
        flush=True,
    )
    print(header, flush=True)
    rows = run(
        PAPER_TABLE,
        args.sensors,
        args.metrics,
        n_problems=args.problems,
        repeat=args.repeat,
        progress=lambda line: print(line, flush=True),
    )
    return 0 if all(r["agree"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
