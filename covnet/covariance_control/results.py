"""The run directory: ``summary.json``, ``arrays.npz``, ``config.json`` and the figures.

Layout of a run directory::

    summary.json    per metric (keyed by registry name under "metrics"): allocation_rate,
                    sensors_per_scan, subsets, P_diag, value, rmse_position, ... (a bounded or
                    greedy search: lower_bound, gap per scan, gap_median, gap_worst); config
                    hash, seed
    arrays.npz      per-scan arrays for notebooks: t, truth, P_d, sensor_ids and, per metric m,
                    x_est.m, P_post.m, P_pred.m, enabled.m, value.m, nees.m (and, when a
                    bounded or greedy search decided, lower_bound.m, gap.m)
    config.json     the normalised config the run used (every default filled in)
    run.json        wall-clock facts: creation time, version, mode, decision times, process
                    layout (what a replay cannot and need not reproduce)
    fig*.png        the figures (see covnet.covariance_control.plots)

Files are written to a temporary name and renamed, so a reader never sees half a file.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from covnet import __version__
from covnet.core.allocation import allocation_rate
from covnet.covariance_control.centre import ManagerResult
from covnet.covariance_control.config import Scenario, config_hash, normalised
from covnet.covariance_control.fusion_rules import rule_for
from covnet.covariance_control.model import build_model
from covnet.covariance_control.simulate import MetricRun, Trajectory, shared_trajectory
from covnet.rundir import (
    ARRAYS,
    CONFIG,
    RUN_INFO,
    SUMMARY,
    read_json,
    utc_now,
    write_json,
    write_npz,
)


def metric_summary(
    run: MetricRun, traj: Trajectory, sensor_ids: tuple[str, ...], switch_scan: int | None
) -> dict[str, Any]:
    """The per-metric block of ``summary.json``."""
    counts = run.enabled.sum(axis=1)
    err = run.x_est - traj.truth[: len(run.x_est)]  # a stopped network run may be partial
    pos_err2 = err[:, 0] ** 2 + err[:, 2] ** 2
    vel_err2 = err[:, 1] ** 2 + err[:, 3] ** 2
    usage = run.enabled.sum(axis=0)
    out: dict[str, Any] = {
        "allocation_rate": allocation_rate(counts.tolist(), len(sensor_ids)),
        "sensors_per_scan": counts.astype(int).tolist(),
        "subsets": [[sensor_ids[j] for j in np.flatnonzero(row)] for row in run.enabled],
        "P_diag": np.diagonal(run.P_post, axis1=1, axis2=2).tolist(),
        "value": run.value.tolist(),
        "rmse_position": float(np.sqrt(pos_err2.mean())),
        "rmse_velocity": float(np.sqrt(vel_err2.mean())),
        "mean_nees": float(run.nees.mean()),
        "usage": {sid: int(u) for sid, u in zip(sensor_ids, usage, strict=True)},
        "subsets_evaluated_median": float(np.median(run.n_evaluated)),
    }
    if run.lower_bound is not None and run.gap is not None:
        # a bounded or greedy search: what it certified at every scan (null: not reported)
        out["lower_bound"] = _finite_or_none(run.lower_bound)
        out["gap"] = _finite_or_none(run.gap)
        gaps = run.gap[np.isfinite(run.gap)]
        out["gap_median"] = float(np.median(gaps)) if gaps.size else None
        out["gap_worst"] = float(gaps.max()) if gaps.size else None
    if switch_scan is not None and 1 < switch_scan <= len(counts):
        cut = switch_scan - 1
        out["usage_before_switch"] = dict(
            zip(sensor_ids, run.enabled[:cut].sum(axis=0).astype(int).tolist(), strict=True)
        )
        out["usage_after_switch"] = dict(
            zip(sensor_ids, run.enabled[cut:].sum(axis=0).astype(int).tolist(), strict=True)
        )
    return out


def _finite_or_none(a: np.ndarray) -> list[float | None]:
    return [float(v) if np.isfinite(v) else None for v in a.tolist()]


def peer_summary(
    nodes: Mapping[str, MetricRun], traj: Trajectory, sensor_ids: tuple[str, ...]
) -> dict[str, Any]:
    """Peer mode, one metric: each node's own estimate quality and whether all nodes enabled
    the same sensors at every scan (``agreement``; ``disagree_scans`` lists where not)."""
    per_node = {sid: metric_summary(r, traj, sensor_ids, None) for sid, r in nodes.items()}
    runs = list(nodes.values())
    n = min(len(r.enabled) for r in runs)
    disagree = [
        k + 1
        for k in range(n)
        if any(not np.array_equal(r.enabled[k], runs[0].enabled[k]) for r in runs)
    ]
    rmse = [b["rmse_position"] for b in per_node.values()]
    return {
        "agreement": not disagree,
        "disagree_scans": disagree,
        "rmse_position_mean": float(np.mean(rmse)),
        "rmse_position_worst": float(np.max(rmse)),
        "mean_nees": float(np.mean([b["mean_nees"] for b in per_node.values()])),
        "nodes": {
            sid: {k: b[k] for k in ("rmse_position", "rmse_velocity", "mean_nees")}
            for sid, b in per_node.items()
        },
    }


def write_run(
    out_dir: Path,
    sc: Scenario,
    traj: Trajectory,
    runs: Mapping[str, MetricRun],
    extra: Mapping[str, Any] | None = None,
    run_info: Mapping[str, Any] | None = None,
    node_runs: Mapping[str, Mapping[str, MetricRun]] | None = None,
) -> dict[str, Any]:
    """Write ``summary.json``, ``arrays.npz``, ``config.json`` and ``run.json``; return the
    summary.

    ``summary.json`` holds only what the config, seed and recorded data determine (``extra``
    adds to it), so a replay reproduces it byte for byte; wall-clock facts (creation time,
    decision times, the process layout: ``run_info``) go to ``run.json``.  ``node_runs`` (peer
    mode: metric -> node id -> run) adds each node's block under ``"peer"`` and its arrays
    (``x_est.<metric>.<node>``, ``P_post.<metric>.<node>``, ``nees.<metric>.<node>``); ``runs``
    then holds the first node's run."""
    out_dir.mkdir(parents=True, exist_ok=True)
    ids = sc.sensor_ids
    switch = sc.desired[1].from_scan if len(sc.desired) > 1 else None
    summary: dict[str, Any] = {
        "scenario": sc.name,
        "config_hash": config_hash(sc),
        "seed": sc.seed,
        "scans": sc.scans,
        "sensor_ids": list(ids),
        "desired_switch_scans": [d.from_scan for d in sc.desired],
        "covnet_version": __version__,
        "fusion": fusion_label(sc),
        "metrics": {m: metric_summary(r, traj, ids, switch) for m, r in runs.items()},
    }
    if node_runs:
        summary["peer"] = {m: peer_summary(nodes, traj, ids) for m, nodes in node_runs.items()}
    if extra:
        summary.update(extra)
    info: dict[str, Any] = {
        "created_utc": utc_now(),
        "covnet_version": __version__,
        "decision_time_median_s": {m: float(np.median(r.decision_s)) for m, r in runs.items()},
    }
    info.update(run_info or {})
    arrays: dict[str, np.ndarray] = {
        "t": traj.t,
        "truth": traj.truth,
        "P_d": traj.P_d,
        "sensor_ids": np.array(ids),
        "metrics": np.array(list(runs)),
    }
    for m, r in runs.items():
        arrays[f"x_est.{m}"] = r.x_est
        arrays[f"P_post.{m}"] = r.P_post
        arrays[f"P_pred.{m}"] = r.P_pred
        arrays[f"enabled.{m}"] = r.enabled
        arrays[f"value.{m}"] = r.value
        arrays[f"nees.{m}"] = r.nees
        if r.lower_bound is not None and r.gap is not None:
            arrays[f"lower_bound.{m}"] = r.lower_bound
            arrays[f"gap.{m}"] = r.gap
    for m, nodes in (node_runs or {}).items():
        for sid, r in nodes.items():
            arrays[f"x_est.{m}.{sid}"] = r.x_est
            arrays[f"P_post.{m}.{sid}"] = r.P_post
            arrays[f"nees.{m}.{sid}"] = r.nees
    write_npz(out_dir / ARRAYS, arrays)
    write_json(out_dir / CONFIG, normalised(sc))
    write_json(out_dir / RUN_INFO, info)
    write_json(out_dir / SUMMARY, summary)
    return summary


def fusion_label(sc: Scenario) -> str:
    """The fusion structure in one word: ``central``, ``info``, ``ci`` (with its objective:
    ``ci-det``), or ``peer-<rule>-<graph>``."""
    f, label = sc.fusion, rule_for(sc.fusion).label()
    return f"peer-{label}-{f.peer.graph}" if f.mode == "peer" else label


def load_summary(run_dir: Path) -> dict[str, Any]:
    summary: dict[str, Any] = read_json(run_dir / SUMMARY)
    return summary


def write_network_run(
    out: Path, sc: Scenario, result: ManagerResult, run_info: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The manager's run directory (and the replay's): the same files as ``covnet run`` for
    the scans done, plus ``network.json`` (the bus's own record) and the failures seen; safe
    to call repeatedly while the run goes on."""
    model = build_model(sc)
    traj = shared_trajectory(model)
    n_sensors = len(model.sensor_ids)
    runs = {m: log.as_run(n_sensors) for m, log in result.episodes.items() if log.value}
    extra: dict[str, Any] = {
        "completed": result.completed,
        "scans_completed": {m: len(log.value) for m, log in result.episodes.items()},
        "failures": {
            m: [{k: v for k, v in ev.items() if k != "detected_ns"} for ev in log.failures]
            for m, log in result.episodes.items()
        },
    }
    info: dict[str, Any] = {
        "mode": "network",
        "scans_completed": extra["scans_completed"],
        "failure_detected_ns": {
            m: [ev for ev in log.failures if "detected_ns" in ev]
            for m, log in result.episodes.items()
        },
    }
    info.update(run_info or {})
    summary = write_run(out, sc, traj, runs, extra=extra, run_info=info)
    write_json(out / "network.json", result.stats.as_dict())
    return summary
