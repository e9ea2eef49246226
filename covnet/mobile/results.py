"""The mobile run directory: ``summary.json``, ``arrays.npz``, ``config.json``, ``run.json``.

``summary.json`` (spec §8.2, issue 7)::

    kind, scenario, config_hash, seed, scans, solver, covnet_version, target_ids, sensor_ids
    targets.<id>:   rmse_position_m, rmse_position_second_half_m, missed_detection_rate,
                    missed_detection_rate_first_half, _second_half, miss_given_assigned,
                    unobserved_scans
    overall:        the same over all targets (RMSE pooled over targets and scans)
    usage_cost_total                          Σ b_jρ over the chosen pairs (raw units)
    platform_travel_m.<id>, .total            path length of every platform
    decisions:      mode_conflicts_resolved, fractional_vertices, solver_status_counts
    optimality:     (with compare_exact) decisions, share_lp_post_worse, mean_gap, max_gap,
                    conflicts_resolved, mean_integrality_gap, exact_not_optimal,
                    per_decision: J_lp, J_lp_post, J_star, J_relax, gap, conflicts

"Second half" is scans ``K//2 + 1 .. K``.  A missed detection is a (target, scan) without a
detection, unobserved targets included; "given assigned" counts only the assigned ones.
Relative gaps are ``(J_LP+post − J*) / |J*|``; a decision counts as worse when its gap exceeds
1e-9.  The integrality gap is ``(J* − J_relax) / |J*|``.

``summary.json`` is a function of the config and the seed alone; the wall-clock facts go to
``run.json``: ``decision_time_s`` (``cost_tensor``, ``solver``, ``comparison``: ``{mean,
median, p95}``; comparison: the other solver and the relaxation, with ``compare_exact``),
creation time, version.  Files are written to a temporary name and renamed
(:mod:`covnet.runs.rundir`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from covnet import __version__
from covnet.mobile.config import MobileConfig, config_hash, normalised
from covnet.mobile.simulate import MobileRun
from covnet.runs.rundir import (
    ARRAYS,
    CONFIG,
    FILE_DIGESTS,
    RUN_INFO,
    SUMMARY,
    read_json,
    utc_now,
    write_json,
    write_npz,
)

if TYPE_CHECKING:
    from covnet.runs.export import Episode

WORSE_TOL = 1e-9


def _rate(x: np.ndarray) -> float | None:
    """The share of ``x`` that is true; None (JSON ``null``) over no scan: ``NaN`` made
    ``summary.json`` invalid JSON (a target never assigned, the first half of one scan)."""
    return float(x.mean()) if x.size else None


def _stats(t: np.ndarray) -> dict[str, float]:
    return {
        "mean": float(t.mean()),
        "median": float(np.median(t)),
        "p95": float(np.percentile(t, 95)),
    }


def _finite(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _target_block(err2: np.ndarray, missed: np.ndarray, assigned: np.ndarray) -> dict[str, Any]:
    """err2, missed, assigned: (K, ...) arrays of one target or of all targets."""
    K = err2.shape[0]
    h = K // 2
    return {
        "rmse_position_m": float(np.sqrt(err2.mean())),
        "rmse_position_second_half_m": float(np.sqrt(err2[h:].mean())),
        "missed_detection_rate": _rate(missed),
        "missed_detection_rate_first_half": _rate(missed[:h]),
        "missed_detection_rate_second_half": _rate(missed[h:]),
        "miss_given_assigned": _rate(missed[assigned]),
        "unobserved_scans": int(np.count_nonzero(~assigned)),
    }


def summarise(cfg: MobileConfig, run: MobileRun) -> dict[str, Any]:
    """The content of ``summary.json`` for one run: a function of config and seed alone."""
    e = run.x_est[1:] - run.truth[1:]
    err2 = e[..., 0] ** 2 + e[..., 2] ** 2  # (K, M)
    missed = ~run.detected
    assigned = run.assign >= 0
    targets = {
        tid: _target_block(err2[:, i], missed[:, i], assigned[:, i])
        for i, tid in enumerate(cfg.target_ids)
    }
    travel = np.linalg.norm(np.diff(run.platforms, axis=0), axis=2).sum(axis=0)
    codes, counts = np.unique(run.status, return_counts=True)
    summary: dict[str, Any] = {
        "kind": "mobile",
        "scenario": cfg.name,
        "config_hash": config_hash(cfg),
        "seed": cfg.seed,
        "scans": cfg.scans,
        "solver": run.solver,
        "covnet_version": __version__,
        "target_ids": list(cfg.target_ids),
        "sensor_ids": list(cfg.sensor_ids),
        "targets": targets,
        "overall": _target_block(err2, missed, assigned),
        "usage_cost_total": float(run.usage.sum()),
        "platform_travel_m": {
            **{sid: float(t) for sid, t in zip(cfg.sensor_ids, travel, strict=True)},
            "total": float(travel.sum()),
        },
        "decisions": {
            "mode_conflicts_resolved": int(run.conflicts[run.conflicts >= 0].sum()),
            "fractional_vertices": int(run.fractional.sum()),
            "solver_status_counts": {
                str(int(c)): int(n) for c, n in zip(codes, counts, strict=True)
            },
        },
    }
    done = np.isfinite(run.J_star)
    if (run.exact_status >= 0).any():  # compare_exact ran: every decision solved or left out
        # (a run whose every MILP timed out lost the whole block, its count of them with it)
        g = run.gap[done]
        js = run.J_star[done]
        integ = (js - run.J_relax[done]) / np.abs(js)
        some = bool(done.any())
        summary["optimality"] = {
            "decisions": int(done.sum()),
            "share_lp_post_worse": float(np.mean(g > WORSE_TOL)) if some else None,
            "mean_gap": float(g.mean()) if some else None,
            "max_gap": float(g.max()) if some else None,
            "conflicts_resolved": int(run.conflicts[done].sum()),
            "mean_integrality_gap": _finite(np.nanmean(integ)) if some else None,
            # compared decisions the MILP proved no optimum for (a time-out): left out above
            "exact_not_optimal": int(np.count_nonzero(run.exact_status > 0)),
            "per_decision": {
                "J_lp": [_finite(v) for v in run.J_lp],
                "J_lp_post": [_finite(v) for v in run.J_post],
                "J_star": [_finite(v) for v in run.J_star],
                "J_relax": [_finite(v) for v in run.J_relax],
                "gap": [_finite(v) for v in run.gap],
                "conflicts": [int(v) for v in run.conflicts],
            },
        }
    return summary


def decision_times(run: MobileRun) -> dict[str, dict[str, float]]:
    """``run.json``'s ``decision_time_s``: the wall times of the decision's parts."""
    t = {"cost_tensor": _stats(run.cost_s), "solver": _stats(run.solve_s)}
    done = np.isfinite(run.J_star)
    if done.any():
        t["comparison"] = _stats(run.compare_s[done])
    return t


def write_run(
    out_dir: Path, cfg: MobileConfig, run: MobileRun, run_info: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Write the run directory (``run_info`` replaces ``run.json``'s defaults); return the
    summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = summarise(cfg, run)
    arrays = run.arrays()
    arrays["target_ids"] = np.array(cfg.target_ids)
    arrays["sensor_ids"] = np.array(cfg.sensor_ids)
    digest = write_npz(out_dir / ARRAYS, arrays)
    write_json(out_dir / CONFIG, normalised(cfg))
    info: dict[str, Any] = {
        "created_utc": utc_now(),
        "covnet_version": __version__,
        "mode": "in-process",
        "kind": "mobile",
        "decision_time_s": decision_times(run),
    }
    write_json(out_dir / SUMMARY, summary)
    # last: a run.json says the results are whole
    write_json(out_dir / RUN_INFO, {**info, **(run_info or {}), FILE_DIGESTS: {ARRAYS: digest}})
    return summary


def load_summary(run_dir: Path) -> dict[str, Any]:
    summary: dict[str, Any] = read_json(run_dir / SUMMARY)
    return summary


def tracks(cfg: MobileConfig, run_dir: Path) -> list[Episode]:
    """``covnet export`` (:mod:`covnet.runs.export`): the run's one episode (named after its
    solver), every target's truth and track at rows ``0..K`` (row 0: the start, the initial
    estimate), ``t = k T``."""
    # start-up: the export's readers only for covnet export
    from covnet.runs.export import Episode, StateSeries, read_arrays

    a = read_arrays(run_dir, "truth", "x_est", "P_post", "target_ids")
    n = min(a["x_est"].shape[0], a["truth"].shape[0])
    scan = np.arange(n, dtype=np.int64)
    t = scan * float(cfg.scan_period_s)
    tids = [str(x) for x in a["target_ids"]]
    truths = tuple(StateSeries(tid, scan, t, a["truth"][:n, i]) for i, tid in enumerate(tids))
    est = tuple(
        StateSeries(tid, scan, t, a["x_est"][:n, i], a["P_post"][:n, i])
        for i, tid in enumerate(tids)
    )
    return [Episode(str(cfg.solver), truths, est)]
