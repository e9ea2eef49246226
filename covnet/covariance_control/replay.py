"""``covnet replay RUN_DIR``: rebuild a network run from its recording alone and check that it
reproduces the run's ``summary.json`` byte for byte (the proof that the recording lost nothing).

Inputs (from the run directory): ``config.json`` (the normalised config), ``run.json`` (the
``episodes`` list: the metric of each episode index; the ``run_id``) and ``recording.mcap``.

What is taken from the recording, decoded strictly (:func:`covnet.messages.decode_as`; a payload
that does not decode is counted by reason and skipped, never used):

- the manager's :class:`~covnet.messages.Status` per ``(episode, scan)`` (key
  ``status_key(run)``; the first one received): ``enabled``, ``fused``, ``failed``, ``value``,
  ``trace_P``;
- the sensors' :class:`~covnet.messages.Measurement` per ``(episode, scan, sensor)`` (key
  ``measurement_key(run, sensor)`` naming the payload's ``sensor_id``; the first one received
  that the manager would accept: ``z`` ``(1, 2)``, ``R`` ``(2, 2)`` symmetric positive
  definite);
- the manager's :class:`~covnet.messages.Track` per ``(episode, scan)`` (a cross-check only).

In the decentralized centre modes (``fusion.mode: info | ci``) the sensors' keys carry
:class:`~covnet.messages.LocalTrack` s instead of measurements, and the steps below are the
manager's for those modes (:func:`covnet.covariance_control.decentral.decide_rule` over the local
filters' covariance mirror, the rule's fusion).  A peer-mode
run has no centre to replay (a :class:`ReplayError` says so).

Per episode ``e`` (metric ``m = episodes[e]``) and scan ``k = 1, 2, ...`` while a Status of
``(e, k)`` was recorded, exactly the manager's steps (``manager.covariance``)::

    x⁻, P⁻ = predict_step(x, P)                                 (x, P: initial_estimate at k=1)
    U      = {index(s) : s in Status.failed}
    D      = decide(model, P⁻, k, m, unavailable=U)             (must equal Status.enabled)
    x, P   = fuse(model, (x⁻, P⁻), [(index(s), z_s, R_s) for s in Status.fused])
    NEES   = (x - x_true(k))ᵀ inv(P) (x - x_true(k))            (truth_trajectory of the seed)

with the failure events derived from the changes of ``Status.failed`` between scans as the
manager derives them from its membership view.  The result is written by the manager's own
writer (:func:`covnet.covariance_control.results.write_network_run`) into ``RUN_DIR/replay/`` (or
``out``): the same ``summary.json``, ``arrays.npz``, ``config.json``; ``run.json`` says
``"mode": "replay"``; ``network.json`` has empty counters (a replay has no network); plus
``replay.json``, the :class:`ReplayReport`.  The two ``summary.json`` files are then compared byte
for byte.  Also reported as differences: a recomputed allocation, objective value, ``tr P`` or fused
track that differs from what the manager recorded, a fused sensor without a recorded measurement, a
missing Status, a run id or config hash in the recording's metadata that is not the run's.

``completed`` is true when every episode has all its scans; ``scans_completed`` counts the
scans with a Status.  Not recoverable from a recording: an episode the manager had started but
stopped before its first command (a Ctrl-C in that instant) is absent from the replay's
``scans_completed`` while the manager listed it with 0 scans.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from covnet import messages as msg
from covnet.core.kalman import nees
from covnet.covariance_control.centre import (
    CentreFilter,
    EpisodeLog,
    ManagerResult,
    usable_track,
)
from covnet.covariance_control.config import Scenario, config_hash, from_dict
from covnet.covariance_control.fusion_rules import rule_for
from covnet.covariance_control.model import (
    build_model,
    initial_estimate,
    predict_step,
    truth_trajectory,
    usable_measurement,
)
from covnet.covariance_control.results import write_network_run
from covnet.recording import META_RUN, RecordedSample, RecordingReader, key_kind, read_metadata
from covnet.rundir import RUN_INFO, SUMMARY, write_json
from covnet.runtime_stats import NetStats

__all__ = ["RECORDING", "REPLAY_DIR", "ReplayError", "ReplayReport", "replay_run"]

RECORDING = "recording.mcap"
REPLAY_DIR = "replay"
REPORT = "replay.json"
MAX_LISTED = 10
"""Differences listed per kind (the rest are counted)."""


class ReplayError(RuntimeError):
    """The run directory cannot be replayed at all (a file missing or unreadable)."""


@dataclass
class ReplayReport:
    """``identical``: the replayed ``summary.json`` equals the original byte for byte and the
    recomputed allocations, values and tracks equal the recorded ones.  ``differences``: what
    did not (human-readable, the first few of each kind).  ``notes``: facts about the recording
    that are not differences (skipped payloads, damage).  ``counts``: what was read."""

    identical: bool
    differences: list[str]
    out_dir: Path
    notes: list[str] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "identical": self.identical,
            "differences": self.differences,
            "notes": self.notes,
            "counts": self.counts,
        }


class _Differences:
    """Differences grouped by kind, at most :data:`MAX_LISTED` listed per kind."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self._per_kind: dict[str, int] = {}

    def add(self, kind: str, text: str) -> None:
        n = self._per_kind.get(kind, 0) + 1
        self._per_kind[kind] = n
        if n <= MAX_LISTED:
            self.lines.append(text)

    def finish(self) -> list[str]:
        out = list(self.lines)
        for kind, n in self._per_kind.items():
            if n > MAX_LISTED:
                out.append(f"... and {n - MAX_LISTED} more differences of kind {kind!r}")
        return out


@dataclass
class _Recorded:
    """What the replay uses from the recording, keyed by (episode, scan[, sensor])."""

    status: dict[tuple[int, int], msg.Status] = field(default_factory=dict)
    track: dict[tuple[int, int], msg.Track] = field(default_factory=dict)
    meas: dict[tuple[int, int, str], Any] = field(default_factory=dict)  # or LocalTrack
    counts: dict[str, int] = field(default_factory=dict)

    def count(self, what: str) -> None:
        self.counts[what] = self.counts.get(what, 0) + 1


def _load_recording(
    samples: Iterator[RecordedSample], run_id: str, decentral: bool = False
) -> _Recorded:
    """``decentral``: the sensors' keys carry local tracks (a track rule: ``info``, ``ci``)."""
    rec = _Recorded()
    for s in samples:
        rec.count("samples")
        kind = key_kind(run_id, s.key)
        try:
            if kind == msg.Status.KIND:
                st = msg.decode_as(s.payload, msg.Status)
                rec.count("status")
                if rec.status.setdefault((st.episode, st.scan), st) is not st:
                    rec.count("status_duplicate")
            elif kind == msg.Track.KIND:
                tr = msg.decode_as(s.payload, msg.Track)
                rec.track.setdefault((tr.episode, tr.scan), tr)
            elif kind == msg.Measurement.KIND and decentral:
                lt = msg.decode_as(s.payload, msg.LocalTrack)
                rec.count("local_track")
                if lt.sensor_id != msg.parse_measurement_key(s.key) or not usable_track(lt):
                    rec.count("skipped:invalid_local_track")
                elif rec.meas.setdefault((lt.episode, lt.scan, lt.sensor_id), lt) is not lt:
                    rec.count("local_track_duplicate")
            elif kind == msg.Measurement.KIND:
                m = msg.decode_as(s.payload, msg.Measurement)
                rec.count("measurement")
                # the manager's acceptance test (manager.covariance._Loop._take), bar the timing
                if m.sensor_id != msg.parse_measurement_key(s.key) or not usable_measurement(
                    m.z, m.R
                ):
                    rec.count("skipped:invalid_measurement")
                elif rec.meas.setdefault((m.episode, m.scan, m.sensor_id), m) is not m:
                    rec.count("measurement_duplicate")
        except msg.WireError as exc:
            rec.count(f"skipped:{exc.reason}")
    return rec


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ReplayError(f"cannot read {path}: {exc}") from None


def replay_run(run_dir: Path, out: Path | None = None) -> ReplayReport:
    """Replay ``run_dir`` from its recording into ``out`` (default ``run_dir/replay``) and
    compare (module docstring).  Raises :class:`ReplayError` when a needed file is missing."""
    run_dir = Path(run_dir)
    out_dir = Path(out) if out is not None else run_dir / REPLAY_DIR
    for name in ("config.json", RUN_INFO, SUMMARY, RECORDING):
        if not (run_dir / name).is_file():
            raise ReplayError(f"{run_dir} has no {name}: not a recorded network run")
    sc = from_dict(_read_json(run_dir / "config.json"), str(run_dir / "config.json"))
    if sc.fusion.mode == "peer":
        raise ReplayError(
            f"{run_dir} is a peer-mode run: there is no fusion centre to re-fuse (each node's "
            "own estimates are in its arrays.npz); replay covers central, info and ci runs"
        )
    info = _read_json(run_dir / RUN_INFO)
    metrics = info.get("episodes")
    if not isinstance(metrics, list) or not all(isinstance(m, str) for m in metrics):
        raise ReplayError(f"{run_dir / RUN_INFO} has no 'episodes' list (not a network run?)")
    diffs = _Differences()
    notes: list[str] = []

    meta_run = read_metadata(run_dir / RECORDING).get(META_RUN, {})
    run_id = info.get("run_id") or meta_run.get("run_id")
    if not isinstance(run_id, str):
        raise ReplayError(f"no run id in {run_dir / RUN_INFO} nor in the recording's metadata")
    if meta_run.get("run_id", run_id) != run_id:
        diffs.add("metadata", f"recording: run id {meta_run['run_id']!r}, run.json: {run_id!r}")
    h = config_hash(sc)
    if meta_run.get("config_hash", h) != h:
        diffs.add("metadata", f"recording: config hash {meta_run['config_hash']}, config.json: {h}")
    reader = RecordingReader(run_dir / RECORDING)
    rec = _load_recording(reader.samples(), run_id, rule_for(sc.fusion).tracks)
    if not reader.complete:
        notes.append(
            "recording has no footer (the recorder did not close it: killed?); read up to "
            + ("its last complete record (the last one is cut)" if reader.truncated else "its end")
        )
    if reader.corrupt_chunks:
        notes.append(
            f"recording: {len(reader.corrupt_chunks)} corrupt chunk(s) skipped at "
            f"bytes {reader.corrupt_chunks[:5]}"
        )
    if reader.orphans:
        notes.append(f"recording: {reader.orphans} message(s) of an unknown channel skipped")
    if reader.error:
        notes.append(f"recording: {reader.error}")
    skipped = {k: v for k, v in rec.counts.items() if k.startswith("skipped:")}
    if skipped:
        notes.append(f"payloads skipped (not used by the replay): {skipped}")

    result = _rebuild(sc, metrics, rec, diffs)
    run_info = {
        "mode": "replay",
        "episodes": metrics,
        "run_id": run_id,
        "replayed_from": str(run_dir),
    }
    write_network_run(out_dir, sc, result, run_info)
    _compare_summaries(run_dir / SUMMARY, out_dir / SUMMARY, diffs)
    differences = diffs.finish()
    report = ReplayReport(
        identical=not differences,
        differences=differences,
        out_dir=out_dir,
        notes=notes,
        counts=dict(sorted(rec.counts.items())),
    )
    write_json(out_dir / REPORT, report.as_dict())
    return report


def _rebuild(
    sc: Scenario, metrics: list[str], rec: _Recorded, diffs: _Differences
) -> ManagerResult:
    """The manager's episode logs, recomputed from the recorded Status and Measurements."""
    model = build_model(sc)
    ids = model.sensor_ids
    truth = truth_trajectory(model)
    result = ManagerResult({}, NetStats())
    completed = True
    for e, metric in enumerate(metrics):
        last = max((k for (ep, k) in rec.status if ep == e), default=0)
        if last == 0:
            completed = False
            continue
        log = result.episodes[metric] = EpisodeLog(metric)
        where = f"episode {e} ({metric})"
        est = initial_estimate(model, sc.filter.initial_estimate)
        centre = CentreFilter(sc, model)  # the manager's own filter steps
        failed_prev: frozenset[str] = frozenset()
        for k in range(1, model.scans + 1):
            st = rec.status.get((e, k))
            if st is None:
                if k <= last:
                    diffs.add(
                        "status",
                        f"{where}: no Status of scan {k} recorded (scans up "
                        f"to {last} are); the replay of this episode stops at scan {k - 1}",
                    )
                break
            pred = predict_step(model, est)
            failed = frozenset(st.failed)
            for sid in sorted(failed ^ failed_prev):
                log.failures.append(
                    {"sensor": sid, "scan": k, "event": "failed" if sid in failed else "rejoined"}
                )
            failed_prev = failed
            unavailable = frozenset(ids.index(s) for s in failed if s in ids)
            t0 = time.perf_counter()
            alloc = centre.decide(pred.P, k, metric, unavailable)
            decision_s = time.perf_counter() - t0
            enabled = tuple(ids[j] for j in alloc.subset)
            if enabled != st.enabled:
                diffs.add(
                    "allocation",
                    f"{where} scan {k}: replayed allocation {list(enabled)}"
                    f" != recorded {list(st.enabled)}",
                )
            elif float(alloc.value) != st.value:
                diffs.add(
                    "value",
                    f"{where} scan {k}: replayed objective {float(alloc.value)!r}"
                    f" != recorded {st.value!r}",
                )
            got: dict[str, Any] = {}
            for sid in st.fused:
                m = rec.meas.get((e, k, sid))
                if m is None or sid not in ids:
                    diffs.add(
                        "measurement",
                        f"{where} scan {k}: the manager fused {sid} but no "
                        "valid measurement of it is recorded",
                    )
                    continue
                got[sid] = m
            for token in st.refiltered or ():  # the late ones the manager re-filtered
                sid, _, scan = token.rpartition(":")
                m = rec.meas.get((e, int(scan), sid)) if scan.isdigit() else None
                if m is None or not centre.insert_late(m):
                    diffs.add(
                        "refiltered",
                        f"{where} scan {k}: the manager re-filtered {token} but the replay "
                        "cannot (no valid recorded message, or not insertable)",
                    )
            pred = centre.prior(pred)
            est = centre.fuse(k, pred, got)
            if float(np.trace(est.P)) != st.trace_P:
                diffs.add(
                    "trace_P",
                    f"{where} scan {k}: replayed tr P {float(np.trace(est.P))!r}"
                    f" != recorded {st.trace_P!r}",
                )
            tr = rec.track.get((e, k))
            if tr is not None and not (np.array_equal(tr.x, est.x) and np.array_equal(tr.P, est.P)):
                dx = float(np.max(np.abs(tr.x - est.x)))
                diffs.add(
                    "track",
                    f"{where} scan {k}: replayed estimate differs from the "
                    f"recorded Track (max |dx| = {dx:.6g})",
                )
            log.record(
                len(ids), alloc, pred, est, nees(est, truth[k - 1]), decision_s, sorted(st.fused)
            )
        if len(log.value) < model.scans:
            completed = False
    result.completed = completed
    return result


def _compare_summaries(original: Path, replayed: Path, diffs: _Differences) -> None:
    a, b = original.read_bytes(), replayed.read_bytes()
    if a == b:
        return
    try:
        ja, jb = json.loads(a), json.loads(b)
    except ValueError:
        diffs.add("summary", f"{original} is not valid JSON")
        return
    paths: list[str] = []
    _json_diff(ja, jb, "", paths, limit=500)
    paths.sort(key=_depth)  # stable: the shallowest (most telling) differences first
    if not paths:  # same data, different bytes (formatting, key order)
        diffs.add("summary", "summary.json: same content but different bytes (format/order)")
    for p in paths:
        diffs.add("summary", f"summary.json {p}")


def _json_diff(a: Any, b: Any, path: str, out: list[str], limit: int = 50) -> None:
    """Append ``path: original != replayed`` for the first ``limit`` differing leaves."""
    if len(out) >= limit:
        return
    if isinstance(a, dict) and isinstance(b, dict):
        if list(a) != list(b):
            out.append(f"{path or '.'}: keys {list(a)} != {list(b)}")
        for k in a:
            if k in b:
                _json_diff(a[k], b[k], f"{path}.{k}" if path else k, out, limit)
        return
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{path}: length {len(a)} != {len(b)}")
        for i, (x, y) in enumerate(zip(a, b, strict=False)):
            _json_diff(x, y, f"{path}[{i}]", out, limit)
        return
    if a != b or type(a) is not type(b):
        out.append(f"{path}: {_short(a)} (original) != {_short(b)} (replayed)")


def _depth(line: str) -> int:
    path = line.split(":", 1)[0]
    return path.count(".") + path.count("[")


def _short(v: Any) -> str:
    text = json.dumps(v)
    return text if len(text) <= 80 else text[:77] + "..."
