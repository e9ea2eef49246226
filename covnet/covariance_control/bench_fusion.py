"""Benchmark: covariance-intersection candidates for the allocator (``ci_candidates``).

The allocator of the decentralized mode needs, every scan, the CI covariance of
``{P_prior} ∪ {P_local[j] : j in D_i}`` for every non-empty subset ``D_i`` of the ``Ns`` sensors
(:func:`covnet.core.fusion.ci_candidates`, one batched call).  This times that call for each
weight rule and sensor count, on a realistic problem (:func:`paper_problem`): the paper's
sensors (the table cycled beyond 8 with larger sigmas, as ``covnet bench`` does:
:func:`covnet.covariance_control.bench_allocation.paper_like_gains`), local filters that measured at
every scan for a few scans, the fused prior their CI predicted.

Baseline (``Ns = 8``, optimising rules): the straightforward way, a plain loop of
``scipy.optimize.minimize`` (SLSQP on the simplex, from equal weights) per subset; the row gets
its time, the speed-up, and the largest amount by which the batched optimum is worse than SLSQP's
(relative in det P resp. tr P; negative: ours is better).

Run: ``python -m covnet.covariance_control.bench_fusion``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from covnet.core.allocation import subset_covariance
from covnet.core.fusion import CI_OBJECTIVES, ci_candidates
from covnet.core.gaussian import Mat
from covnet.core.kalman import predict_covariance
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.covariance_control.bench_allocation import DEFAULT_P0, PAPER_TABLE, paper_like_gains

#: sensor counts whose baseline (a scipy loop over every subset) is timed
BASELINE_SENSORS = (8,)


def subset_masks(n_sensors: int) -> NDArray[np.bool_]:
    """All ``2^Ns − 1`` non-empty subsets as a ``(2^Ns − 1, Ns)`` bool matrix (row ``i`` is the
    binary code ``i + 1``, sensor 0 in the lowest bit)."""
    codes = np.arange(1, 2**n_sensors)
    return ((codes[:, None] >> np.arange(n_sensors)) & 1).astype(bool)


def paper_problem(
    n_sensors: int,
    scans: int = 5,
    *,
    base_table: Sequence[tuple[float, float, float]] = PAPER_TABLE,
    T: float = 1.0,
    sigma_a: float = 0.5,
    P0: Mat = DEFAULT_P0,
) -> tuple[Mat, NDArray[np.float64]]:
    """``(P_prior, P_local)`` of the paper scenario after ``scans`` scans, covariances only.

    Each sensor's local filter predicts (``P⁻ = F P Fᵀ + Q``) and measures every scan
    (``P = (P⁻⁻¹ + J_j)⁻¹``); the fused filter predicts and takes the det-CI of its prediction
    and all local posteriors.  Returned: the fused prediction for the next scan and each local
    posterior at that scan (what the sensor would have if it measured).
    """
    gains = paper_like_gains(base_table, n_sensors)
    F, Q = cv_transition(T), dwna_process_noise(T, sigma_a)
    P0 = np.asarray(P0, dtype=np.float64)
    local = np.broadcast_to(P0, (n_sensors, *P0.shape))
    fused = P0
    every = np.ones((1, n_sensors), dtype=bool)
    for _ in range(scans + 1):
        local = subset_covariance(predict_covariance(local, F, Q), gains)
        prior = predict_covariance(fused, F, Q)
        fused = ci_candidates(prior, local, every, "det")[0]
    return prior, local


def _objective(w: NDArray[np.float64], Y: NDArray[np.float64], objective: str) -> float:
    P = np.linalg.inv(np.tensordot(w, Y, axes=1))
    return float(np.linalg.slogdet(P)[1] if objective == "det" else np.trace(P))


def scipy_loop(
    P_prior: Mat, P_local: NDArray[np.float64], masks: NDArray[np.bool_], objective: str
) -> NDArray[np.float64]:
    """The optimum objective (``log det P`` or ``tr P``) of every subset by a plain loop of
    SLSQP on the simplex, from equal weights: the baseline."""
    Y_all = np.linalg.inv(np.concatenate([P_prior[None], P_local]))
    out = np.empty(masks.shape[0])
    for i, row in enumerate(masks):
        Y = Y_all[np.concatenate([[True], row])]
        n = Y.shape[0]
        res = minimize(  # type: ignore[call-overload]  # scipy-stubs: constraints as dicts
            _objective,
            np.full(n, 1.0 / n),
            args=(Y, objective),
            method="SLSQP",
            bounds=[(0.0, 1.0)] * n,
            constraints=[{"type": "eq", "fun": lambda w: w.sum() - 1.0}],
            options={"ftol": 1e-12, "maxiter": 200},
        )
        out[i] = _objective(
            np.clip(res.x, 0.0, None) / np.clip(res.x, 0.0, None).sum(), Y, objective
        )
    return out


def _values(P: NDArray[np.float64], objective: str) -> NDArray[np.float64]:
    return np.linalg.slogdet(P)[1] if objective == "det" else np.trace(P, axis1=1, axis2=2)


def run_bench(
    sensors: Sequence[int] = (8, 12, 16),
    objectives: Sequence[str] = CI_OBJECTIVES,
    repeat: int = 5,
    baseline: bool = True,
) -> list[dict[str, object]]:
    """Time :func:`covnet.core.fusion.ci_candidates` over all non-empty subsets.

    Rows ``{"objective", "n_sensors", "n_subsets", "median_s", "per_subset_us", "baseline_s",
    "speedup", "worse_than_scipy"}``: the median wall time (``time.perf_counter``) of one call
    over ``repeat`` calls (after one warm-up call), per subset in microseconds; for
    ``n_sensors`` in :data:`BASELINE_SENSORS` and the optimising rules (``baseline=True``) the
    time of :func:`scipy_loop` (run once), the ratio, and ``max (ours − scipy) / s`` over the
    subsets (``s = 1`` for det, whose objective is a log, ``tr P`` for trace); else ``None``.
    """
    rows: list[dict[str, object]] = []
    for Ns in sensors:
        P_prior, P_local = paper_problem(Ns)
        masks = subset_masks(Ns)
        for objective in objectives:
            P = ci_candidates(P_prior, P_local, masks, objective)
            times = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                ci_candidates(P_prior, P_local, masks, objective)
                times.append(time.perf_counter() - t0)
            med = float(np.median(times))
            row: dict[str, object] = {
                "objective": objective,
                "n_sensors": Ns,
                "n_subsets": int(masks.shape[0]),
                "median_s": med,
                "per_subset_us": med / masks.shape[0] * 1e6,
                "baseline_s": None,
                "speedup": None,
                "worse_than_scipy": None,
            }
            if baseline and Ns in BASELINE_SENSORS and objective != "fast":
                t0 = time.perf_counter()
                ref = scipy_loop(P_prior, P_local, masks, objective)
                base = time.perf_counter() - t0
                ours = _values(P, objective)
                scale = 1.0 if objective == "det" else np.abs(ref)
                row.update(
                    baseline_s=base,
                    speedup=base / med,
                    worse_than_scipy=float(np.max((ours - ref) / scale)),
                )
            rows.append(row)
    return rows


def format_table(rows: Sequence[dict[str, object]]) -> str:
    """The rows of :func:`run_bench` as a fixed-width text table."""

    def opt(value: object, fmt: str) -> str:
        return "-" if value is None else format(value, fmt)

    lines = [
        f"{'objective':<9} {'Ns':>3} {'subsets':>7} {'median_s':>10} {'us/subset':>9} "
        f"{'scipy_s':>8} {'speedup':>8} {'worse_than_scipy':>16}"
    ]
    for r in rows:
        lines.append(
            f"{r['objective']:<9} {r['n_sensors']:>3} {r['n_subsets']:>7} "
            f"{r['median_s']:>10.5f} {r['per_subset_us']:>9.1f} "
            f"{opt(r['baseline_s'], '8.3f'):>8} {opt(r['speedup'], '8.0f'):>8} "
            f"{opt(r['worse_than_scipy'], '16.2e'):>16}"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sensors", type=int, nargs="+", default=[8, 12, 16])
    parser.add_argument("--objectives", nargs="+", default=list(CI_OBJECTIVES))
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--no-baseline", action="store_true")
    args = parser.parse_args(argv)
    rows = run_bench(args.sensors, args.objectives, args.repeat, baseline=not args.no_baseline)
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
