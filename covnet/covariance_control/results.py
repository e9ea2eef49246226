"""The run directory: ``summary.json``, ``arrays.npz``, ``config.json`` and the figures.

Layout of a run directory::

    summary.json    per metric (keyed by registry name under "metrics"): allocation_rate,
                    sensors_per_scan, subsets, P_diag, value, rmse_position, ... (a bounded or
                    greedy search: lower_bound, gap per scan, gap_median, gap_worst, and
                    relative to the distance from doing nothing gap_nothing per scan,
                    gap_nothing_median, gap_nothing_worst); config hash, seed
    arrays.npz      per-scan arrays for notebooks: t, truth, P_d, sensor_ids and, per metric m,
                    x_est.m, P_post.m, P_pred.m, enabled.m, value.m, nees.m (and, when a
                    bounded or greedy search decided, lower_bound.m, gap.m)
    config.json     the normalised config the run used (every default filled in)
    run.json        wall-clock facts: creation time, version, mode, decision times, process
                    layout (what a replay cannot and need not reproduce)
    fig*.png        the figures (see covnet.covariance_control.plots)

Files are written to a temporary name and renamed, so a reader never sees half a file.

Many targets (a config with ``targets:``, :func:`write_targets_run`): the same files, with per
metric a ``targets`` block per target (position and velocity RMSE, mean NEES and NIS with their
95 % χ² bands, sensors per scan, ``f(P_t, P_d,t)`` per scan, ``tr P_t`` and ``tr P_d,t``), OSPA
and GOSPA per scan, and each sensor's dwell counts per target; ``arrays.npz`` holds the arrays
of every target (``truth`` ``(T, K, 4)``, per metric ``assignment``, ``x_est``, ``P_post``,
``nees``, ``ospa``, ...).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from covnet import __version__
from covnet.batches.stats import median
from covnet.core.allocation import allocation_rate
from covnet.core.allocation.search_problem import gap_from_nothing
from covnet.core.metrics import METRICS
from covnet.covariance_control.config import Scenario, config_hash, normalised
from covnet.covariance_control.config.allocation import policy_fields
from covnet.covariance_control.fusion_rules import rule_for
from covnet.covariance_control.model import build_model
from covnet.covariance_control.simulate import (
    MetricRun,
    TargetsRun,
    Trajectory,
    shared_trajectory,
)
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
    from covnet.covariance_control.centre import ManagerResult
    from covnet.covariance_control.targets import TargetsModel
    from covnet.runs.export import Episode


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
        # (null: not reported; a peer network's nodes do not report it: it said 0)
        "subsets_evaluated_median": (
            median(run.n_evaluated) if (run.n_evaluated >= 0).all() else None
        ),
    }
    if run.lower_bound is not None and run.gap is not None:
        # a bounded or greedy search: what it certified at every scan (null: not reported)
        out["lower_bound"] = _finite_or_none(run.lower_bound)
        out["gap"] = _finite_or_none(run.gap)
        gaps = run.gap[np.isfinite(run.gap)]
        out["gap_median"] = median(gaps) if gaps.size else None
        out["gap_worst"] = float(gaps.max()) if gaps.size else None
        # the same certificate relative to the distance from doing nothing, f(P⁻, P_d) - value
        # (P⁻ the scan's recorded prediction): what says something where the optimum is near 0
        K = len(run.value)
        nothing = METRICS[run.metric].fn(run.P_pred[:K], traj.P_d[:K])
        out.update(_gap_nothing_fields(run.value, run.lower_bound, nothing))
    if switch_scan is not None and 1 < switch_scan <= len(counts):
        cut = switch_scan - 1
        out["usage_before_switch"] = dict(
            zip(sensor_ids, run.enabled[:cut].sum(axis=0).astype(int).tolist(), strict=True)
        )
        out["usage_after_switch"] = dict(
            zip(sensor_ids, run.enabled[cut:].sum(axis=0).astype(int).tolist(), strict=True)
        )
    return out


def _gap_nothing_fields(value: np.ndarray, lower: np.ndarray, nothing: Any) -> dict[str, Any]:
    """``gap_nothing`` per scan (:func:`~covnet.core.allocation.search_problem.
    gap_from_nothing`; null where no bound was reported or the decision did no better than
    doing nothing), its median and worst over the scans that have one."""
    g = gap_from_nothing(value, lower, nothing)
    fin = g[np.isfinite(g)]
    return {
        "gap_nothing": _finite_or_none(g),
        "gap_nothing_median": median(fin) if fin.size else None,
        "gap_nothing_worst": float(fin.max()) if fin.size else None,
    }


def _finite_or_none(a: np.ndarray) -> list[float | None]:
    return [float(v) if np.isfinite(v) else None for v in a.tolist()]


def peer_summary(
    nodes: Mapping[str, MetricRun],
    traj: Trajectory,
    sensor_ids: tuple[str, ...],
    disagree: list[int] | None = None,
) -> dict[str, Any]:
    """Peer mode, one metric: each node's own estimate quality and whether all nodes enabled
    the same sensors at every scan (``agreement``; ``disagree_scans`` lists where not: given,
    from every scan the nodes reported (a network run's:
    :func:`covnet.covariance_control.peer_run.disagreement`), or from the runs' scans)."""
    per_node = {sid: metric_summary(r, traj, sensor_ids, None) for sid, r in nodes.items()}
    runs = list(nodes.values())
    if disagree is None:
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
    disagree: Mapping[str, list[int]] | None = None,
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
    summary.update(policy_fields(sc.allocation))
    if node_runs:
        summary["peer"] = {
            m: peer_summary(nodes, traj, ids, (disagree or {}).get(m))
            for m, nodes in node_runs.items()
        }
    if extra:
        summary.update(extra)
    info: dict[str, Any] = {
        "created_utc": utc_now(),
        "covnet_version": __version__,
        "decision_time_median_s": {m: median(r.decision_s) for m, r in runs.items()},
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
    info[FILE_DIGESTS] = {ARRAYS: write_npz(out_dir / ARRAYS, arrays)}
    write_json(out_dir / CONFIG, normalised(sc))
    write_json(out_dir / SUMMARY, summary)
    write_json(out_dir / RUN_INFO, info)  # last: a run.json says the results are whole
    return summary


def fusion_label(sc: Scenario) -> str:
    """The fusion structure in one word: ``central``, ``info``, ``ci`` (with its objective:
    ``ci-det``), or ``peer-<rule>-<graph>``."""
    f, label = sc.fusion, rule_for(sc.fusion).label()
    return label if f.has_centre else f"peer-{label}-{f.peer.graph}"


def load_summary(run_dir: Path) -> dict[str, Any]:
    summary: dict[str, Any] = read_json(run_dir / SUMMARY)
    return summary


def write_network_run(
    out: Path, sc: Scenario, result: ManagerResult, run_info: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The manager's run directory (and the replay's): the same files as ``covnet run`` for
    the scans done, plus ``network.json`` (the bus's own record) and the failures seen; safe
    to call repeatedly while the run goes on."""
    if sc.surveillance is not None:
        return _write_surveillance_network_run(out, sc, result, run_info)
    if sc.multitarget:
        return _write_targets_network_run(out, sc, result, run_info)
    model = build_model(sc)
    traj = shared_trajectory(model)
    n_sensors = len(model.sensor_ids)
    runs = {m: log.as_run(n_sensors) for m, log in result.episodes.items() if log.value}
    extra, info = _network_facts(result)
    info.update(run_info or {})
    summary = write_run(out, sc, traj, runs, extra=extra, run_info=info)
    write_json(out / "network.json", result.stats.as_dict())
    return summary


# --------------------------------------------------------------------------------------------
# many targets
# --------------------------------------------------------------------------------------------


def target_trajectory(tm: TargetsModel) -> dict[str, np.ndarray]:
    """What every metric's run shares: ``t`` ``(K,)``, ``truth`` ``(T, K, 4)`` and ``P_d``
    ``(T, K, 4, 4)``."""
    from covnet.covariance_control import targets  # start-up: configs with targets only

    scans = np.arange(1, tm.scans + 1)
    return {
        "t": scans * tm.T,
        "truth": targets.truth_trajectories(tm),
        "P_d": np.stack([np.stack([tg.desired(int(k)) for k in scans]) for tg in tm.targets]),
        "weights": np.array([[tg.weight(int(k)) for k in scans] for tg in tm.targets]),
    }


def ospa_series(run: TargetsRun, truth: np.ndarray, c: float, p: float) -> tuple[Any, Any]:
    """OSPA and GOSPA (``α = 2``) per scan of the estimated positions against the true ones
    (every target has its track: no initiation, no deletion)."""
    from covnet.core.ospa import gospa, ospa  # start-up: scipy.optimize for these runs only

    n = run.x_est.shape[1]
    o, g = np.empty(n), np.empty(n)
    for k in range(n):
        X = truth[:, k][:, [0, 2]]
        Y = run.x_est[:, k][:, [0, 2]]
        o[k] = ospa(X, Y, c, p)
        g[k] = gospa(X, Y, c, p).distance
    return o, g


def _band(values: np.ndarray, dof: int) -> list[float]:
    from covnet.core.consistency import chi2_band  # start-up: scipy.stats for these runs only

    b = chi2_band(dof, max(int(values.size), 1))
    return [b.low, b.high]


def targets_summary(
    run: TargetsRun, traj: Mapping[str, np.ndarray], tm: TargetsModel
) -> dict[str, Any]:
    """The per-metric block of a many-target ``summary.json`` (module docstring)."""
    from covnet.core.consistency import mean_chi2_band  # start-up: scipy.stats, these runs only

    ids, tids = tm.sensor_ids, tm.target_ids
    K = run.assignment.shape[0]
    truth = traj["truth"][:, :K]
    enabled = run.enabled
    counts = enabled.sum(axis=1)
    o, g = ospa_series(run, truth, tm.ospa_c, tm.ospa_p)
    single = _band(np.ones(1), 4)  # one scan's NEES band
    per_target: dict[str, Any] = {}
    for t, tid in enumerate(tids):
        err = run.x_est[t] - truth[t]
        nis_n = int(run.nis_n[t].sum())
        nis_dof = int(run.nis_dof[t].sum())
        block: dict[str, Any] = {
            "rmse_position": float(np.sqrt((err[:, 0] ** 2 + err[:, 2] ** 2).mean())),
            "rmse_velocity": float(np.sqrt((err[:, 1] ** 2 + err[:, 3] ** 2).mean())),
            "max_position_error": float(np.hypot(err[:, 0], err[:, 2]).max()),
            "mean_nees": float(run.nees[t].mean()),
            "nees_band_95": _band(run.nees[t], 4),
            "nees_share_in_single_band": float(
                np.mean((run.nees[t] >= single[0]) & (run.nees[t] <= single[1]))
            ),
            "mean_nis": float(run.nis_sum[t].sum() / nis_n) if nis_n else None,
            "nis_band_95": list(mean_chi2_band(nis_dof, nis_n)) if nis_n else None,
            "nis_updates": nis_n,
            "nis_mean_dof": nis_dof / nis_n if nis_n else None,
            "sensors_per_scan": (run.assignment == t).sum(axis=1).astype(int).tolist(),
            "f": run.values[t].tolist(),
            "trace_P": np.trace(run.P_post[t], axis1=1, axis2=2).tolist(),
            "trace_Pd": np.trace(traj["P_d"][t, :K], axis1=1, axis2=2).tolist(),
            "sensors_on_target_share": float((run.assignment == t).sum() / max(counts.sum(), 1)),
        }
        per_target[tid] = block
    dwell = {
        sid: {
            **{tid: int((run.assignment[:, j] == t).sum()) for t, tid in enumerate(tids)},
            "off": int((run.assignment[:, j] < 0).sum()),
        }
        for j, sid in enumerate(ids)
    }
    out: dict[str, Any] = {
        "allocation_rate": allocation_rate(counts.tolist(), len(ids)),
        "sensors_per_scan": counts.astype(int).tolist(),
        "assignments": [
            {ids[j]: tids[a] for j, a in enumerate(row) if a >= 0}
            for row in run.assignment.tolist()
        ],
        "value": run.value.tolist(),
        "usage": {sid: int(u) for sid, u in zip(ids, enabled.sum(axis=0), strict=True)},
        "dwell_counts": dwell,
        "targets": per_target,
        "ospa": o.tolist(),
        "gospa": g.tolist(),
        "mean_ospa": float(o.mean()),
        "mean_gospa": float(g.mean()),
        "returns_per_dwell": float(run.returns[run.returns >= 0].mean())
        if (run.returns >= 0).any()
        else None,
        "dwells_that_updated": float(run.used.sum() / max(int(enabled.sum()), 1)),
        "subsets_evaluated_median": median(run.n_evaluated),
    }
    required = sorted(tm.base.constraints.required)
    if required:
        # scans each required sensor was off: failed, covering no target, or one more than
        # its targets had room for under max_per_target (targets.assignable)
        out["required_off"] = {ids[j]: int((run.assignment[:, j] < 0).sum()) for j in required}
    if run.lower_bound is not None and run.gap is not None:
        # a bounded or greedy search: what it certified at every scan (null: not reported)
        out["lower_bound"] = _finite_or_none(run.lower_bound)
        out["gap"] = _finite_or_none(run.gap)
        gaps = run.gap[np.isfinite(run.gap)]
        out["gap_median"] = median(gaps) if gaps.size else None
        out["gap_worst"] = float(gaps.max()) if gaps.size else None
        # relative to the distance from doing nothing: F(nothing) = Σ_t w_t f(P⁻_t, P_d,t) (the
        # targets in order, as the assignment's F = Σ_t w_t f_t sums them)
        f = METRICS[run.metric].fn
        nothing = np.zeros(K)
        for t in range(len(tids)):
            nothing = nothing + traj["weights"][t, :K] * f(run.P_pred[t, :K], traj["P_d"][t, :K])
        out.update(_gap_nothing_fields(run.value, run.lower_bound, nothing))
    return out


def write_targets_run(
    out_dir: Path,
    sc: Scenario,
    tm: TargetsModel,
    runs: Mapping[str, TargetsRun],
    extra: Mapping[str, Any] | None = None,
    run_info: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """:func:`write_run` for a many-target scenario (module docstring): ``summary.json``,
    ``arrays.npz``, ``config.json`` and ``run.json``; returns the summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    traj = target_trajectory(tm)
    summary: dict[str, Any] = {
        "scenario": sc.name,
        "config_hash": config_hash(sc),
        "seed": sc.seed,
        "scans": sc.scans,
        "sensor_ids": list(tm.sensor_ids),
        "target_ids": list(tm.target_ids),
        "sensor_models": [s.kind for s in tm.sensors],
        "desired_switch_scans": {tg.id: list(tg.desired_from) for tg in tm.targets},
        "covnet_version": __version__,
        "fusion": fusion_label(sc),
        "association": tm.method,
        "ospa": {"cutoff_m": tm.ospa_c, "order": tm.ospa_p},
        "metrics": {m: targets_summary(r, traj, tm) for m, r in runs.items()},
    }
    summary.update(policy_fields(sc.allocation))
    if extra:
        summary.update(extra)
    info: dict[str, Any] = {
        "created_utc": utc_now(),
        "covnet_version": __version__,
        "decision_time_median_s": {m: median(r.decision_s) for m, r in runs.items()},
    }
    info.update(run_info or {})
    arrays: dict[str, np.ndarray] = {
        **traj,
        "sensor_ids": np.array(tm.sensor_ids),
        "target_ids": np.array(tm.target_ids),
        "metrics": np.array(list(runs)),
    }
    for m, r in runs.items():
        o, g = ospa_series(r, traj["truth"][:, : r.assignment.shape[0]], tm.ospa_c, tm.ospa_p)
        arrays[f"assignment.{m}"] = r.assignment
        arrays[f"enabled.{m}"] = r.enabled
        arrays[f"value.{m}"] = r.value
        arrays[f"values.{m}"] = r.values
        arrays[f"x_est.{m}"] = r.x_est
        arrays[f"P_post.{m}"] = r.P_post
        arrays[f"P_pred.{m}"] = r.P_pred
        arrays[f"nees.{m}"] = r.nees
        arrays[f"nis_sum.{m}"] = r.nis_sum
        arrays[f"nis_dof.{m}"] = r.nis_dof
        arrays[f"nis_n.{m}"] = r.nis_n
        arrays[f"returns.{m}"] = r.returns
        arrays[f"used.{m}"] = r.used
        arrays[f"ospa.{m}"] = o
        arrays[f"gospa.{m}"] = g
        if r.lower_bound is not None and r.gap is not None:
            arrays[f"lower_bound.{m}"] = r.lower_bound
            arrays[f"gap.{m}"] = r.gap
    info[FILE_DIGESTS] = {ARRAYS: write_npz(out_dir / ARRAYS, arrays)}
    write_json(out_dir / CONFIG, normalised(sc))
    write_json(out_dir / SUMMARY, summary)
    write_json(out_dir / RUN_INFO, info)  # last: a run.json says the results are whole
    return summary


def _write_targets_network_run(
    out: Path, sc: Scenario, result: ManagerResult, run_info: dict[str, Any] | None
) -> dict[str, Any]:
    """:func:`write_network_run` of a many-target run (the episodes are
    :class:`~covnet.covariance_control.targets_centre.TargetEpisodeLog` s)."""
    from covnet.covariance_control import targets  # start-up: configs with targets only

    tm = targets.build(sc)
    return _write_episodes(out, result, run_info, lambda runs, extra, info: write_targets_run(
        out, sc, tm, runs, extra=extra, run_info=info
    ))  # fmt: skip


def _write_surveillance_network_run(
    out: Path, sc: Scenario, result: ManagerResult, run_info: dict[str, Any] | None
) -> dict[str, Any]:
    """:func:`write_network_run` of a surveillance run (the episodes are
    :class:`~covnet.covariance_control.surveillance_log.SurveillanceLog` s)."""
    # start-up: the surveillance world only for configs with surveillance
    from covnet.covariance_control import surveillance
    from covnet.covariance_control.surveillance_results import write_surveillance_run

    sm = surveillance.build(sc)
    return _write_episodes(out, result, run_info, lambda runs, extra, info: write_surveillance_run(
        out, sc, sm, runs, extra=extra, run_info=info
    ))  # fmt: skip


def _write_episodes(
    out: Path, result: ManagerResult, run_info: dict[str, Any] | None, write: Any
) -> dict[str, Any]:
    """The episodes' runs (``as_run()`` of each with a scan), the network's facts, then
    ``write(runs, extra, info)`` (the kind's run writer) and ``network.json``."""
    runs = {m: log.as_run() for m, log in result.episodes.items() if log.value}
    extra, info = _network_facts(result)
    info.update(run_info or {})
    summary: dict[str, Any] = write(runs, extra, info)
    write_json(out / "network.json", result.stats.as_dict())
    return summary


def _network_facts(result: ManagerResult) -> tuple[dict[str, Any], dict[str, Any]]:
    """What a network run adds to ``summary.json`` (``completed``, scans, failures) and to
    ``run.json`` (when each failure was seen)."""
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
    return extra, info


def tracks(sc: Scenario, run_dir: Path) -> list[Episode]:
    """``covnet export`` (:mod:`covnet.runs.export`): per metric of the run (``arrays.npz``'s
    order), every target's truth and fused track over the scans the metric's episode did
    (scans ``1..K'`` at ``t``); a single target is ``T1``.  A surveillance run: its targets
    while they exist and its confirmed tracks
    (:func:`~covnet.covariance_control.surveillance_results.surveillance_tracks`)."""
    if sc.surveillance is not None:  # tracks that start and end: their own layout
        # start-up: the surveillance results only for a surveillance run's export
        from covnet.covariance_control.surveillance_results import surveillance_tracks

        return surveillance_tracks(run_dir)
    # start-up: the export's readers only for covnet export
    from covnet.runs.export import Episode, StateSeries, read_arrays, require_arrays

    a = read_arrays(run_dir, "metrics", "t", "truth")
    metrics = [str(m) for m in a["metrics"]]
    need = [f"{f}.{m}" for m in metrics for f in ("x_est", "P_post")]
    if sc.multitarget:
        need.append("target_ids")
    require_arrays(a, run_dir, *need)
    if sc.multitarget:
        tids = [str(x) for x in a["target_ids"]]
        truth, est, cov = a["truth"], {}, {}
        for m in metrics:
            est[m], cov[m] = a[f"x_est.{m}"], a[f"P_post.{m}"]
    else:  # one target: the (K, ...) arrays as a target axis of one
        tids = ["T1"]
        truth = a["truth"][None]
        est = {m: a[f"x_est.{m}"][None] for m in metrics}
        cov = {m: a[f"P_post.{m}"][None] for m in metrics}
    t = a["t"]
    out = []
    for m in metrics:
        n = est[m].shape[1]  # a network run stopped early: the scans the episode did
        scan = np.arange(1, n + 1, dtype=np.int64)
        out.append(
            Episode(
                m,
                tuple(StateSeries(tid, scan, t[:n], truth[i, :n]) for i, tid in enumerate(tids)),
                tuple(
                    StateSeries(tid, scan, t[:n], est[m][i], cov[m][i])
                    for i, tid in enumerate(tids)
                ),
            )
        )
    return out
