"""The run directory of a surveillance run (a config with ``surveillance:``): the files of
every covariance-control run (:mod:`covnet.covariance_control.results`) with what surveillance
measures (spec ``surveillance.md`` §5).

``summary.json`` per metric: ``gospa_mean`` and its parts' means (``gospa_localisation``,
``gospa_missed``, ``gospa_false``: the ``p``-th powers GOSPA sums), ``ospa_mean``,
``cardinality_error_mean`` (``|confirmed - true|``), ``time_to_confirm`` per target (scans from
its appearance to the first confirmed track on it; null: never) and its mean over the confirmed
ones, ``missed_targets`` (never confirmed), ``track_breaks``, ``id_switches``,
``tracks_started``, ``false_tracks`` (confirmed tracks never on a target), ``search_share``
(dwells on search over all dwells), ``undetected_mass_final`` (``Σ u_c`` after the last scan),
``value_mean``.  ``arrays.npz``: ``truth`` ``(n, K, 4)`` (NaN: absent), ``exists``, ``cells``
and per metric the per-scan series (``gospa.m``, ``gospa_loc.m``, ``gospa_missed.m``,
``gospa_false.m``, ``ospa.m``, ``n_truth.m``, ``n_confirmed.m``, ``n_tentative.m``, ``u.m``
``(K, C)``, ``search_dwells.m``, ``track_dwells.m``, ``value.m``) and the tracks of every scan
flattened (``track_rows.m``: ``scan, id, state (0 tentative, 1 confirmed, 2 deleted), x (4),
P (16)`` per row).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from covnet import __version__
from covnet.batches.stats import median
from covnet.covariance_control.config import Scenario, config_hash, normalised
from covnet.covariance_control.config.allocation import policy_fields
from covnet.covariance_control.surveillance import SurveillanceModel
from covnet.covariance_control.surveillance_log import SurveillanceRun
from covnet.runs.rundir import (
    ARRAYS,
    CONFIG,
    FILE_DIGESTS,
    RUN_INFO,
    SUMMARY,
    utc_now,
    write_json,
    write_npz,
)

if TYPE_CHECKING:
    from covnet.runs.export import Episode

__all__ = [
    "STATES",
    "surveillance_summary",
    "surveillance_tracks",
    "track_id",
    "track_rows",
    "write_surveillance_run",
]

#: a track's state as ``track_rows`` codes it
STATES = {"tentative": 0, "confirmed": 1, "deleted": 2}


def _mean(x: np.ndarray) -> float | None:
    return float(np.mean(x)) if x.size else None


def surveillance_summary(r: SurveillanceRun, truth_ids: tuple[str, ...]) -> dict[str, Any]:
    """The per-metric block of ``summary.json`` (module docstring)."""
    ttc = r.time_to_confirm
    seen = np.isfinite(ttc)
    dwells = r.search_dwells.sum() + r.track_dwells.sum()
    return {
        "gospa_mean": _mean(r.gospa),
        "gospa_localisation": _mean(r.gospa_loc),
        "gospa_missed": _mean(r.gospa_missed),
        "gospa_false": _mean(r.gospa_false),
        "ospa_mean": _mean(r.ospa),
        "cardinality_error_mean": _mean(np.abs(r.n_confirmed - r.n_truth).astype(float)),
        "time_to_confirm": {
            tid: (None if not math.isfinite(v) else float(v))
            for tid, v in zip(truth_ids, ttc.tolist(), strict=True)
        },
        "time_to_confirm_mean": float(ttc[seen].mean()) if seen.any() else None,
        "missed_targets": int((~seen).sum()),
        "track_breaks": int(r.breaks),
        "id_switches": int(r.id_switches),
        "tracks_started": int(r.n_tracks_started),
        "false_tracks": int(r.n_false_tracks),
        "search_dwells": int(r.search_dwells.sum()),
        "track_dwells": int(r.track_dwells.sum()),
        "search_share": float(r.search_dwells.sum() / dwells) if dwells else 0.0,
        "undetected_mass_final": float(r.u_sum[-1]) if r.u_sum.size else 0.0,
        "value_mean": _mean(r.value),
    }


def track_rows(r: SurveillanceRun) -> np.ndarray:
    """Every scan's tracks as rows ``[scan, id, state, x (4), P (16)]`` (module docstring)."""
    out = [
        [k + 1, tid, STATES[st], *x.tolist(), *P.reshape(-1).tolist()]
        for k, rows in enumerate(r.tracks)
        for (tid, st, x, P) in rows
    ]
    return np.array(out, dtype=np.float64).reshape(-1, 23)


def write_surveillance_run(
    out_dir: Path,
    sc: Scenario,
    sm: SurveillanceModel,
    runs: Mapping[str, SurveillanceRun],
    extra: Mapping[str, Any] | None = None,
    run_info: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """``summary.json``, ``arrays.npz``, ``config.json`` and ``run.json`` of a surveillance
    run; returns the summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {
        "scenario": sc.name,
        "config_hash": config_hash(sc),
        "seed": sc.seed,
        "scans": sc.scans,
        "sensor_ids": list(sm.sensor_ids),
        "truth_ids": list(sm.truth_ids),
        "sensor_models": [s.kind for s in sm.tm.sensors],
        "covnet_version": __version__,
        "association": "jpda",  # what the centre runs (pda, the default, is its one-track case)
        "ospa": {"cutoff_m": sm.tm.ospa_c, "order": sm.tm.ospa_p},
        "search_weight": 0.0 if sm.spec.search is None else sm.spec.search.weight,
        "cells": sm.n_cells,
        "metrics": {m: surveillance_summary(r, sm.truth_ids) for m, r in runs.items()},
    }
    # the policy and its budget, as every other kind's summary names them (covariance control,
    # the default, adds nothing: its summary is what it was)
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
        "t": sm.T * np.arange(1, sm.scans + 1),
        "truth": sm.truth,
        "exists": sm.exists,
        "cells": sm.cells,
        "sensor_ids": np.array(sm.sensor_ids),
        "truth_ids": np.array(sm.truth_ids),
        "metrics": np.array(list(runs)),
    }
    for m, r in runs.items():
        for key in (
            "gospa",
            "gospa_loc",
            "gospa_missed",
            "gospa_false",
            "ospa",
            "n_truth",
            "n_confirmed",
            "n_tentative",
            "u",
            "search_dwells",
            "track_dwells",
            "value",
        ):
            arrays[f"{key}.{m}"] = getattr(r, key)
        arrays[f"track_rows.{m}"] = track_rows(r)
        arrays[f"time_to_confirm.{m}"] = r.time_to_confirm
    info[FILE_DIGESTS] = {ARRAYS: write_npz(out_dir / ARRAYS, arrays)}
    write_json(out_dir / CONFIG, normalised(sc))
    write_json(out_dir / SUMMARY, summary)
    write_json(out_dir / RUN_INFO, info)  # last: a run.json says the results are whole
    return summary


def track_id(n: int) -> str:
    """The id of covnet's track number ``n`` in an export (``track-17``): a track's own number,
    not a target's (a surveillance track is started from detections, not cued)."""
    return f"track-{n}"


def surveillance_tracks(run_dir: Path) -> list[Episode]:
    """``covnet export`` of a surveillance run (:mod:`covnet.runs.export`): per metric, every
    target's truth over the scans it exists (``exists``; a target that never appeared in the
    scans done: no series) and every *confirmed* track over the scans it was confirmed at
    (``track_rows`` with state 1; tentative and deleted rows are left out), with its id
    :func:`track_id`, time ``t`` and posterior ``x``, ``P``.  These are the two sets covnet's
    per-scan GOSPA and OSPA compare (the existing targets against the confirmed tracks'
    positions: :func:`~covnet.core.surveillance.continuity.evaluate_continuity`), so a metric
    on the export gives covnet's.  A network run stopped early: the scans its metric
    did (``gospa.m``'s length)."""
    # start-up: the export's readers only for covnet export
    from covnet.runs.export import Episode, StateSeries, read_arrays, require_arrays

    a = read_arrays(run_dir, "metrics", "t", "truth", "exists", "truth_ids")
    metrics = [str(m) for m in a["metrics"]]
    require_arrays(a, run_dir, *(f"{f}.{m}" for m in metrics for f in ("gospa", "track_rows")))
    t, truth, exists = a["t"], a["truth"], a["exists"]
    tids = [str(x) for x in a["truth_ids"]]
    out = []
    for m in metrics:
        n = a[f"gospa.{m}"].shape[0]
        truths = []
        for i, tid in enumerate(tids):
            k = np.flatnonzero(exists[i, :n])
            if k.size:
                truths.append(StateSeries(tid, k + 1, t[k], truth[i, k]))
        rows = a[f"track_rows.{m}"]
        rows = rows[(rows[:, 2] == STATES["confirmed"]) & (rows[:, 0] <= n)]
        tracks = []
        for num in sorted({int(x) for x in rows[:, 1]}):
            r = rows[rows[:, 1] == num]
            r = r[np.argsort(r[:, 0], kind="stable")]
            scan = r[:, 0].astype(np.int64)
            tracks.append(
                StateSeries(track_id(num), scan, t[scan - 1], r[:, 3:7], r[:, 7:].reshape(-1, 4, 4))
            )
        out.append(Episode(m, tuple(truths), tuple(tracks)))
    return out
