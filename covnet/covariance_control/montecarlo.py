"""``covnet mc`` for covariance control: the same config over ``N`` seeds (``seed``,
``seed + 1``, ...; trial 0 is ``covnet run``'s), every metric, means with 95 % intervals.

Each seed is one in-process run of every metric (many targets: :func:`covnet.covariance_control.
simulate.run_targets`; the paper's kind of config: the run ``covnet run`` makes, any fusion
mode or slow links) in a worker process (:func:`covnet.batches.trials.run_trials`: each seed written
to
``OUT/trials`` as it finishes, so the same command resumes), summarised there and sent back
small: its scalars, and per scan the OSPA, each target's ``tr P`` and its sensors.
The rows are ordered by seed whatever order the workers finish in, so ``montecarlo.json``
depends on the config and the seeds only; the wall times go to ``run.json``.

Aggregates, per metric and scalar (and per target): the mean over seeds, the standard deviation
(ddof = 1), the 95 % confidence interval of the mean ``mean ± t_{0.975, N−1} s / √N`` (Student;
one seed: no interval), min and max; per scan the mean OSPA and ``tr P_t`` with the same
interval; per target the seeds whose track was lost (ever further from the truth than the OSPA
cut-off); and the filter's consistency over the whole batch: the mean NEES over every seed and
scan against the 95 % χ² band of ``N · K`` values (approximate: a run's errors are correlated
from scan to scan), likewise the NIS against the band of its summed degrees of freedom.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from covnet import __version__
from covnet.batches.pool import BatchInterrupted
from covnet.batches.stats import NONNEGATIVE, SHARE, interval, interval_text, per_scan_interval
from covnet.batches.trials import Batch, BatchProgress, Outcome, run_trials, trial_hash
from covnet.covariance_control.config import Scenario, config_hash, from_dict, normalised
from covnet.runs.rundir import CONFIG, RUN_INFO, utc_now, write_json

MC_FILE = "montecarlo.json"
MC_KIND = "covariance_control-montecarlo"

_TARGET_SCALARS = (
    "rmse_position",
    "rmse_velocity",
    "max_position_error",
    "mean_nees",
    "mean_nis",
    "sensors_per_scan_mean",
)
_SCALARS = ("allocation_rate", "mean_ospa", "mean_gospa")
_BOUNDS = {"allocation_rate": SHARE}
"""The range of a scalar other than ``>= 0``."""


def run_seed(cfg_data: Mapping[str, Any], seed: int) -> dict[str, Any]:
    """One seed in a worker (top level so it pickles): every metric's run, summarised."""
    sc = from_dict({**cfg_data, "seed": seed}, f"seed {seed}")
    if sc.surveillance is not None:
        # start-up: the surveillance batch only for configs with surveillance
        from covnet.covariance_control.surveillance_batch import seed_row

        return seed_row(cfg_data, seed)
    return _targets_seed(sc) if sc.multitarget else _paper_seed(sc)


def _targets_seed(sc: Scenario) -> dict[str, Any]:
    # start-up: the workers import what their config needs
    from covnet.covariance_control import targets
    from covnet.covariance_control.results import target_trajectory, targets_summary
    from covnet.covariance_control.simulate import run_targets

    tm = targets.build(sc)
    traj = target_trajectory(tm)
    out: dict[str, Any] = {"seed": sc.seed, "metrics": {}, "decision_time_s": {}}
    for m in sc.allocation.metrics:
        r = run_targets(sc, m, tm)
        s = targets_summary(r, traj, tm)
        row: dict[str, Any] = {k: s[k] for k in _SCALARS}
        row["ospa"] = s["ospa"]
        row["targets"] = {}
        for tid, t in s["targets"].items():
            row["targets"][tid] = {
                "rmse_position": t["rmse_position"],
                "rmse_velocity": t["rmse_velocity"],
                "max_position_error": t["max_position_error"],
                "mean_nees": t["mean_nees"],
                "mean_nis": t["mean_nis"],
                "sensors_per_scan_mean": float(np.mean(t["sensors_per_scan"])),
                "nees_sum": float(np.sum(r.nees[tm.target_ids.index(tid)])),
                "nees_n": int(r.nees.shape[1]),
                "nis_sum": float(r.nis_sum[tm.target_ids.index(tid)].sum()),
                "nis_dof": int(r.nis_dof[tm.target_ids.index(tid)].sum()),
                "nis_n": int(r.nis_n[tm.target_ids.index(tid)].sum()),
                "trace_P": t["trace_P"],
                "sensors_per_scan": t["sensors_per_scan"],
            }
        out["metrics"][m] = row
        out["decision_time_s"][m] = float(np.median(r.decision_s))
    return out


def _paper_seed(sc: Scenario) -> dict[str, Any]:
    # start-up: the workers import what their config needs
    from covnet.covariance_control.decentral_sim import run_mode
    from covnet.covariance_control.latency_sim import run_latency
    from covnet.covariance_control.model import build_model
    from covnet.covariance_control.results import metric_summary
    from covnet.covariance_control.simulate import shared_trajectory

    model = build_model(sc)
    traj = shared_trajectory(model)
    slow = not sc.network.latency.is_ideal(sc.sensor_ids)
    out: dict[str, Any] = {"seed": sc.seed, "metrics": {}, "decision_time_s": {}}
    switch = sc.desired[1].from_scan if len(sc.desired) > 1 else None
    for m in sc.allocation.metrics:
        r = run_latency(sc, m, model)[0] if slow else run_mode(sc, m, model)[0]
        s = metric_summary(r, traj, sc.sensor_ids, switch)
        out["metrics"][m] = {
            "allocation_rate": s["allocation_rate"],
            "targets": {
                "T1": {
                    "rmse_position": s["rmse_position"],
                    "rmse_velocity": s["rmse_velocity"],
                    "mean_nees": s["mean_nees"],
                    "sensors_per_scan_mean": float(np.mean(s["sensors_per_scan"])),
                    "nees_sum": float(np.sum(r.nees)),
                    "nees_n": int(r.nees.size),
                    "trace_P": np.trace(r.P_post, axis1=1, axis2=2).tolist(),
                    "sensors_per_scan": s["sensors_per_scan"],
                }
            },
        }
        out["decision_time_s"][m] = float(np.median(r.decision_s))
    return out


def _run_seed_list(task: tuple[Mapping[str, Any], list[int]]) -> list[dict[str, Any]]:
    """The seeds of one task of the batch layer (:mod:`covnet.batches.trials`)."""
    data, seeds = task
    return [run_seed(data, s) for s in seeds]


POINT = "seeds"
"""The one point of the Monte Carlo (its trials are the seeds)."""


def trial_key(sc: Scenario) -> str:
    """The hash that keys the Monte Carlo's trials: the config without its seed (each trial
    sets its own; the config's seed is the first trial's) and its evaluation settings (which
    change no trial: a changed burn-in refused the batch's own directory), as the sweep's."""
    data = normalised(sc)
    data.pop("seed", None)
    data.pop("evaluation", None)
    return trial_hash("mc", {"kind": "covariance_control", "config": data})


def mc_outcome(
    sc: Scenario,
    n: int,
    *,
    out: Path | None = None,
    workers: int | None = None,
    progress: BatchProgress | None = None,
) -> tuple[list[int], list[dict[str, Any]], Outcome]:
    """``(seeds, rows, outcome)`` of ``n`` seeds from the config's, each trial written to
    ``out`` (``OUT/trials``) as it finishes and skipped when it is there already (the same
    command resumes).  Ctrl-C: :class:`covnet.batches.pool.BatchInterrupted` whose ``partial`` is
    the rows of the seeds done from the first on without a gap: ``[(seed, row), ...]``."""
    data = normalised(sc)
    b = Batch("mc", _run_seed_list, lambda point, seeds: (data, seeds), [POINT], first_seed=sc.seed)
    try:
        outcome = run_trials(
            b,
            n,
            out=out,
            key=trial_key(sc) if out is not None else None,
            workers=workers,
            progress=progress,
        )
    except BatchInterrupted as stop:
        done = sorted(((s, r) for (_, s), r in stop.done.items()), key=lambda sr: sr[0])
        stop.partial = [sr for i, sr in enumerate(done) if sr[0] == sc.seed + i]
        raise
    return b.seeds(outcome.seeds[POINT]), outcome.results[POINT], outcome


def aggregate(rows: Sequence[Mapping[str, Any]], cutoff_m: float | None = None) -> dict[str, Any]:
    """Per metric (module docstring); with ``cutoff_m`` (the OSPA cut-off) each target's
    ``lost``: the seeds whose track was ever further than it from the truth."""
    from covnet.core.consistency import chi2_band, mean_chi2_band  # start-up: scipy.stats

    out: dict[str, Any] = {}
    for m in rows[0]["metrics"]:
        per = [r["metrics"][m] for r in rows]
        # every scalar and curve here is >= 0 (rates, distances, NEES, traces, counts)
        blk: dict[str, Any] = {
            k: interval([p[k] for p in per], bounds=_BOUNDS.get(k, NONNEGATIVE))
            for k in _SCALARS
            if k in per[0]
        }
        if "ospa" in per[0]:
            blk["ospa_per_scan"] = per_scan_interval([p["ospa"] for p in per], bounds=NONNEGATIVE)
        blk["targets"] = {}
        for tid in per[0]["targets"]:
            tt = [p["targets"][tid] for p in per]
            tb: dict[str, Any] = {
                k: interval([t[k] for t in tt], bounds=NONNEGATIVE)
                for k in _TARGET_SCALARS
                if k in tt[0]
            }
            n = sum(t["nees_n"] for t in tt)
            band = chi2_band(4, n)
            tb["nees_batch"] = {
                "mean": sum(t["nees_sum"] for t in tt) / n,
                "band_95": [band.low, band.high],
                "values": n,
            }
            if "nis_n" in tt[0]:
                nis_n = sum(t["nis_n"] for t in tt)
                dof = sum(t["nis_dof"] for t in tt)
                tb["nis_batch"] = {
                    "mean": sum(t["nis_sum"] for t in tt) / nis_n if nis_n else None,
                    "band_95": list(mean_chi2_band(dof, nis_n)) if nis_n else None,
                    "values": nis_n,
                }
            if cutoff_m is not None and "max_position_error" in tt[0]:
                tb["lost"] = {
                    "seeds": [
                        r["seed"]
                        for r, t in zip(rows, tt, strict=True)
                        if t["max_position_error"] > cutoff_m
                    ],
                    "cutoff_m": cutoff_m,
                }
            tb["trace_P_per_scan"] = per_scan_interval(
                [t["trace_P"] for t in tt], bounds=NONNEGATIVE
            )
            tb["sensors_per_scan"] = per_scan_interval(
                [t["sensors_per_scan"] for t in tt], bounds=NONNEGATIVE
            )
            blk["targets"][tid] = tb
        out[m] = blk
    return out


def write_mc(
    out_dir: Path, sc: Scenario, seeds: Sequence[int], rows: Sequence[Mapping[str, Any]]
) -> dict[str, Any]:
    """``montecarlo.json`` (the config hash, the seeds, the aggregate and every seed's row:
    what the config and the seeds determine), ``config.json``, then ``run.json`` (wall clock;
    last, as the batch's status that follows: with it the table is whole)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    times = [r["decision_time_s"] for r in rows]
    clean = [{k: v for k, v in r.items() if k != "decision_time_s"} for r in rows]
    if sc.surveillance is not None:
        # start-up: the surveillance batch only for configs with surveillance
        from covnet.covariance_control.surveillance_batch import aggregate as surv_aggregate

        doc = {
            "kind": MC_KIND,
            "scenario": sc.name,
            "config_hash": config_hash(sc),
            "seeds": list(seeds),
            "metrics": list(sc.allocation.metrics),
            "surveillance": True,
            "aggregate": surv_aggregate(clean) if clean else {},
            "per_seed": clean,
        }
        write_json(out_dir / MC_FILE, doc)
        write_json(out_dir / CONFIG, normalised(sc))
        _write_run_info(out_dir, times)
        return doc
    from covnet.covariance_control import targets  # start-up: the desired traces only

    tm = targets.build(sc)
    doc = {
        "kind": MC_KIND,
        "scenario": sc.name,
        "config_hash": config_hash(sc),
        "seeds": list(seeds),
        "metrics": list(sc.allocation.metrics),
        "trace_Pd": {
            tg.id: [float(np.trace(tg.desired(k))) for k in range(1, sc.scans + 1)]
            for tg in tm.targets
        },
        "aggregate": aggregate(clean, sc.ospa.cutoff_m if sc.multitarget else None)
        if clean
        else {},
        "per_seed": clean,
    }
    write_json(out_dir / MC_FILE, doc)
    write_json(out_dir / CONFIG, normalised(sc))
    _write_run_info(out_dir, times)
    return doc


def _write_run_info(out_dir: Path, times: Sequence[Mapping[str, float]]) -> None:
    """``run.json``: the wall clock, each metric's median decision time over the seeds."""
    write_json(
        out_dir / RUN_INFO,
        {
            "created_utc": utc_now(),
            "covnet_version": __version__,
            "kind": MC_KIND,
            "decision_time_median_s": {
                m: float(np.median([t[m] for t in times])) for m in (times[0] if times else {})
            },
        },
    )


def json_rows(doc: Mapping[str, Any]) -> list[dict[str, Any]]:
    """``covnet mc --json``: one row per metric and target, its scalars' intervals (the
    metric's own, such as the allocation rate, in each of its rows), the batch NEES (and NIS)
    and the seeds whose track was lost; the per-scan series stay in ``montecarlo.json``."""
    rows = []
    if doc.get("surveillance"):  # one row per metric: its scalars' intervals
        from covnet.covariance_control.surveillance_batch import SCALARS  # start-up

        for m, blk in doc["aggregate"].items():
            rows.append({"metric": m, "seeds": list(doc["seeds"]),
                         **{k: blk[k] for k in SCALARS}})  # fmt: skip
        return rows
    for m, blk in doc["aggregate"].items():
        own = {k: v for k, v in blk.items() if k in _SCALARS}
        for tid, t in blk["targets"].items():
            row: dict[str, Any] = {"metric": m, "target": tid, "seeds": list(doc["seeds"])}
            row.update(own)
            row.update({k: v for k, v in t.items() if k in _TARGET_SCALARS})
            for k in ("nees_batch", "nis_batch"):
                if k in t:
                    row[k] = t[k]
            if "lost" in t:
                row["lost_seeds"] = t["lost"]["seeds"]
            rows.append(row)
    return rows


def format_table(doc: Mapping[str, Any]) -> str:
    """The headline numbers: per metric and target, means with their 95 % intervals."""

    ci = interval_text

    if doc.get("surveillance"):
        from covnet.covariance_control import surveillance_batch  # start-up

        return surveillance_batch.format_table(doc["aggregate"], len(doc["seeds"]))
    lines = [f"{len(doc['seeds'])} seeds, means with 95 % confidence intervals"]
    for m, blk in doc["aggregate"].items():
        head = f"  {m}: allocation rate {ci(blk['allocation_rate'], '{:.3f}')}"
        if "mean_ospa" in blk:
            head += f", mean OSPA {ci(blk['mean_ospa'])} m, mean GOSPA {ci(blk['mean_gospa'])} m"
        lines.append(head)
        for tid, t in blk["targets"].items():
            nb = t["nees_batch"]
            lost = t.get("lost")
            tail = f", lost in {len(lost['seeds'])} seeds {lost['seeds']}" if lost else ""
            lines.append(
                f"    {tid}: RMSE {ci(t['rmse_position'])} m (median "
                f"{t['rmse_position']['median']:.2f}), NEES {ci(t['mean_nees'])} (median "
                f"{t['mean_nees']['median']:.2f}; batch {nb['mean']:.2f}, 95 % band "
                f"{nb['band_95'][0]:.2f}-{nb['band_95'][1]:.2f}), sensors/scan "
                f"{ci(t['sensors_per_scan_mean'])}{tail}"
            )
    return "\n".join(lines)
