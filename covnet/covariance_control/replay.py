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

Many targets (a config with ``targets:``): the same, with the many-target centre's steps
(:class:`covnet.covariance_control.targets_centre.TargetsCentre`): per scan the assignment is
recomputed from the predictions and ``Status.failed`` and compared with the recorded Command's
enabled set, targets and clutter windows and with the Status; each fused sensor's recorded
returns (``z`` ``(m, dim_z)``, its model's ``R``) are fused per target, and every target's
recomputed estimate is compared with its recorded Track.

The steps shared by every kind's replay (reading the recording, the metadata check, the notes,
the byte-for-byte comparison, ``covnet replay`` itself) are :mod:`covnet.replay_kit`'s.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
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
from covnet.covariance_control.config import KIND, Scenario
from covnet.covariance_control.fusion_rules import rule_for
from covnet.covariance_control.model import (
    build_model,
    initial_estimate,
    predict_step,
    truth_trajectory,
    usable_measurement,
)
from covnet.covariance_control.results import write_network_run
from covnet.recording import RecordedSample
from covnet.replay_kit import (
    RECORDING,
    REPLAY_DIR,
    Differences,
    KindReplay,
    Recorded,
    ReplayError,
    ReplayReport,
    failure_events,
    load_recording,
)
from covnet.runtime_stats import NetStats

__all__ = [
    "RECORDING",
    "REPLAY_DIR",
    "ReplayError",
    "ReplayReport",
    "command",
    "rebuild",
    "replay_run",
]


class CovarianceReplay(KindReplay):
    """The covariance-control kind's parts of a replay (module docstring)."""

    kind = KIND

    def check(self, cfg: Scenario, run_dir: Path) -> None:
        if cfg.fusion.mode == "peer":
            raise ReplayError(
                f"{run_dir} is a peer-mode run: there is no fusion centre to re-fuse (each "
                "node's own estimates are in its arrays.npz); replay covers central, info and "
                "ci runs"
            )

    def load(self, cfg: Scenario, samples: Iterator[RecordedSample], run_id: str) -> Recorded:
        """The Status, Tracks and the sensors' messages the manager would accept (bar their
        timing): a position measurement (``z`` ``(1, 2)``, ``R`` symmetric positive definite),
        or under a track rule a usable local track."""
        if cfg.multitarget:
            # start-up: the many-target steps only for configs with targets
            from covnet.covariance_control import targets
            from covnet.covariance_control.targets_centre import TargetsCentre

            centre = TargetsCentre(targets.build(cfg))
            if cfg.fusion.mode == "info":
                return load_recording(
                    samples,
                    run_id,
                    message=msg.LocalTrack,
                    label="local_track",
                    acceptable=centre.usable_track,
                    commands=True,
                )
            return load_recording(samples, run_id, acceptable=centre.usable, commands=True)
        if rule_for(cfg.fusion).tracks:
            return load_recording(
                samples,
                run_id,
                message=msg.LocalTrack,
                label="local_track",
                acceptable=usable_track,
            )
        return load_recording(samples, run_id, acceptable=lambda m: usable_measurement(m.z, m.R))

    def recompute(
        self, cfg: Scenario, episodes: list[str], rec: Recorded, diffs: Differences
    ) -> ManagerResult:
        if cfg.multitarget:
            return _recompute_targets(cfg, episodes, rec, diffs)
        return _recompute(cfg, episodes, rec, diffs)

    def write(
        self, out: Path, cfg: Scenario, result: ManagerResult, run_info: dict[str, Any]
    ) -> None:
        write_network_run(out, cfg, result, run_info)


REPLAY = CovarianceReplay()
rebuild = REPLAY.rebuild
"""``rebuild(cfg, run_id, episodes, recording, out, run_info=None) -> ReplayReport``
(:meth:`covnet.replay_kit.KindReplay.rebuild`)."""
replay_run = REPLAY.replay_run
"""``replay_run(run_dir, out=None) -> ReplayReport``: replay and compare ``summary.json``."""
command = REPLAY.command
"""``covnet replay RUN_DIR`` of a covariance-control run."""


def _recompute(
    sc: Scenario, metrics: list[str], rec: Recorded, diffs: Differences
) -> ManagerResult:
    """The manager's episode logs, recomputed from the recorded Status and Measurements."""
    model = build_model(sc)
    ids = model.sensor_ids
    truth = truth_trajectory(model)
    result = ManagerResult({}, NetStats())
    completed = True
    for e, metric in enumerate(metrics):
        last = rec.last_scan(e)
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
            log.failures.extend(failure_events(failed_prev, failed, k))
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
            tr = next(iter(rec.tracks.get((e, k), ())), None)  # the first one received
            if tr is not None and not (np.array_equal(tr.x, est.x) and np.array_equal(tr.P, est.P)):
                dx = float(np.max(np.abs(tr.x - est.x)))
                diffs.add(
                    "track",
                    f"{where} scan {k}: replayed estimate differs from the "
                    f"recorded Track (max |dx| = {dx:.6g})",
                )
            log.record(len(ids), alloc, pred, est, nees(est, truth[k - 1]), decision_s)
        if len(log.value) < model.scans:
            completed = False
    result.completed = completed
    return result


def _recompute_targets(
    sc: Scenario, metrics: list[str], rec: Recorded, diffs: Differences
) -> ManagerResult:
    """The many-target manager's episode logs, recomputed from the recorded Commands, Status,
    Measurements and Tracks (module docstring)."""
    # start-up: the many-target steps only for configs with targets
    from covnet.covariance_control import targets
    from covnet.covariance_control.targets_centre import TargetEpisodeLog, TargetsCentre

    tm = targets.build(sc)
    ids, tids = tm.sensor_ids, tm.target_ids
    truth = targets.truth_trajectories(tm)
    result = ManagerResult({}, NetStats())
    completed = True
    for e, metric in enumerate(metrics):
        last = rec.last_scan(e)
        if last == 0:
            completed = False
            continue
        log = result.episodes[metric] = TargetEpisodeLog.start(metric, tm, truth)
        where = f"episode {e} ({metric})"
        lat = sc.network.latency
        history = None
        if not lat.is_ideal(ids) and lat.late == "oosm":
            history = targets.History(tm, lat.oosm_depth, sc.fusion.mode == "info")
        centre = TargetsCentre(tm, history)  # the manager's own steps
        failed_prev: frozenset[str] = frozenset()
        for k in range(1, tm.scans + 1):
            st = rec.status.get((e, k))
            if st is None:
                if k <= last:
                    diffs.add(
                        "status",
                        f"{where}: no Status of scan {k} recorded (scans up to {last} are); "
                        f"the replay of this episode stops at scan {k - 1}",
                    )
                break
            failed = frozenset(st.failed)
            log.failures.extend(failure_events(failed_prev, failed, k))
            failed_prev = failed
            plan = centre.decide(k, metric, frozenset(ids.index(s) for s in failed if s in ids))
            enabled, tasks, windows = centre.command_fields(plan)
            if enabled != st.enabled:
                diffs.add(
                    "allocation",
                    f"{where} scan {k}: replayed allocation {list(enabled)} != recorded "
                    f"{list(st.enabled)}",
                )
            elif float(plan.decision.value) != st.value:
                diffs.add(
                    "value",
                    f"{where} scan {k}: replayed objective {float(plan.decision.value)!r} != "
                    f"recorded {st.value!r}",
                )
            cmd = rec.commands.get((e, k))
            if cmd is not None and (
                cmd.targets != tasks
                or msg.Command(k, 0.0, enabled, 0, windows=windows)
                != msg.Command(k, 0.0, enabled, 0, windows=cmd.windows)
            ):
                diffs.add(
                    "command",
                    f"{where} scan {k}: the replayed targets or clutter windows are not the "
                    "recorded Command's",
                )
            got: dict[str, Any] = {}
            for sid in st.fused:
                m = rec.meas.get((e, k, sid))
                if (
                    m is None
                    or sid not in ids
                    or (isinstance(m, msg.LocalTrack) and not centre.usable_track(m, plan))
                ):
                    diffs.add(
                        "measurement",
                        f"{where} scan {k}: the manager fused {sid} but no valid measurement of "
                        "it is recorded",
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
            prior, posts, dwells = centre.fuse(plan, got)
            trace_P = float(sum(np.trace(g.P) for g in posts))
            if trace_P != st.trace_P:
                diffs.add(
                    "trace_P",
                    f"{where} scan {k}: replayed tr P {trace_P!r} != recorded {st.trace_P!r}",
                )
            recorded = {tr.target_id: tr for tr in rec.tracks.get((e, k), ())[::-1]}
            for tid, g in zip(tids, posts, strict=True):
                tr = recorded.get(tid)
                if tr is not None and not (np.array_equal(tr.x, g.x) and np.array_equal(tr.P, g.P)):
                    diffs.add(
                        "track",
                        f"{where} scan {k}: the replayed estimate of {tid} differs from its "
                        f"recorded Track (max |dx| = {float(np.max(np.abs(tr.x - g.x))):.6g})",
                    )
            log.record(plan, prior, posts, dwells, sorted(st.fused))
        if len(log.value) < tm.scans:
            completed = False
    result.completed = completed
    return result
