"""``covnet replay RUN_DIR``: rebuild a network run from its recording alone and check that it
reproduces the run's ``summary.json`` byte for byte (the proof that the recording lost nothing).

Inputs (from the run directory): ``config.json`` (the normalised config), ``run.json`` (the
``episodes`` list: the metric of each episode index; the ``run_id``) and ``recording.mcap``.

What is taken from the recording, decoded strictly (:func:`covnet.wire.messages.decode_as`; a
payload
that does not decode is counted by reason and skipped, never used): the manager's
:class:`~covnet.wire.messages.Status` and :class:`~covnet.wire.messages.Command` per ``(episode,
scan)``
(the first one received), its :class:`~covnet.wire.messages.Track` s, and the sensors' messages
(:class:`~covnet.wire.messages.Measurement`, or under a track rule :class:`~covnet.wire.messages.
LocalTrack`) whose content the manager would accept, every one per ``(episode, scan, sensor)``
in the order received.

The replay is a third driver of the kind's one scan logic (:class:`covnet.covariance_control.
engine.ScanEngine`, which ``covnet run`` and the manager step too).  Per episode ``e`` (metric
``episodes[e]``) and scan ``k = 1, 2, ...`` while a Status of ``(e, k)`` was recorded::

    failed = Status.failed                      (failure events: its changes between scans)
    plan   = engine.decide(k, failed)           == Status.enabled, Status.value; == the
                                                   Command's targets and clutter windows
    got    = {s: the first recorded message of s for (e, k) that engine.usable passes
              (its content and the validation gate), s in Status.fused}
    late   = engine.insert_late(...) for each "<sensor>:<scan>" in Status.refiltered
    out    = engine.report(plan, engine.fuse(plan, got), got)
             out.trace_P == Status.trace_P;  each target's estimate == its first recorded
             Track, bit for bit

The result is written by the manager's own writer (:func:`covnet.covariance_control.results.
write_network_run`) into ``RUN_DIR/replay/`` (or ``out``): the same ``summary.json``,
``arrays.npz``, ``config.json``; ``run.json`` says ``"mode": "replay"``; ``network.json`` has
empty counters (a replay has no network); plus ``replay.json``, the :class:`ReplayReport`.  The
two ``summary.json`` files are then compared byte for byte; every mismatch above is a
difference too, as is a fused sensor without a usable recorded message, a missing Status, a
run id or config hash in the recording's metadata that is not the run's.

``completed`` is true when every episode has all its scans.  Not recoverable from a
recording: an episode the manager had started but stopped before its first command (a Ctrl-C
in that instant).  A peer-mode run has no centre to replay (a :class:`ReplayError` says so).
The steps shared by every kind's replay (reading the recording, the metadata check, the notes,
the byte-for-byte comparison, ``covnet replay`` itself) are :mod:`covnet.runs.replay_kit`'s.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from covnet.covariance_control.centre import ManagerResult
from covnet.covariance_control.config import KIND, Scenario
from covnet.covariance_control.engine import Outcome, Plan, ScanEngine
from covnet.covariance_control.results import write_network_run
from covnet.runs.recording import RecordedSample
from covnet.runs.replay_kit import (
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
from covnet.wire import messages as msg

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
        if not cfg.fusion.has_centre:
            raise ReplayError(
                f"{run_dir} is a peer-mode run: there is no fusion centre to re-fuse (each "
                "node's own estimates are in its arrays.npz); replay covers central, info and "
                "ci runs"
            )

    def load(self, cfg: Scenario, samples: Iterator[RecordedSample], run_id: str) -> Recorded:
        """The Status, Tracks, Commands and the sensors' messages the manager would accept
        (the engine's content test, bar the scan's own plan): measurements, or under a track
        rule local tracks."""
        engine = ScanEngine(cfg, ["load"])
        engine.start_episode(0)
        if engine.tracks:
            return load_recording(
                samples,
                run_id,
                message=msg.LocalTrack,
                label="local_track",
                acceptable=engine.usable,
                commands=True,
            )
        return load_recording(samples, run_id, acceptable=engine.usable, commands=True)

    def recompute(
        self, cfg: Scenario, episodes: list[str], rec: Recorded, diffs: Differences
    ) -> ManagerResult:
        return _recompute(cfg, episodes, rec, diffs)

    def write(
        self, out: Path, cfg: Scenario, result: ManagerResult, run_info: dict[str, Any]
    ) -> None:
        write_network_run(out, cfg, result, run_info)


REPLAY = CovarianceReplay()
rebuild = REPLAY.rebuild
"""``rebuild(cfg, run_id, episodes, recording, out, run_info=None) -> ReplayReport``
(:meth:`covnet.runs.replay_kit.KindReplay.rebuild`)."""
replay_run = REPLAY.replay_run
"""``replay_run(run_dir, out=None) -> ReplayReport``: replay and compare ``summary.json``."""
command = REPLAY.command
"""``covnet replay RUN_DIR`` of a covariance-control run."""


def _recompute(
    sc: Scenario, metrics: list[str], rec: Recorded, diffs: Differences
) -> ManagerResult:
    """The manager's episode logs, recomputed by stepping the kind's engine with the recorded
    Status, Commands and sensors' messages (module docstring)."""
    engine = ScanEngine(sc, metrics)
    ids = engine.ids
    completed = True
    for e, metric in enumerate(metrics):
        last = rec.last_scan(e)
        if last == 0:
            completed = False
            continue
        engine.start_episode(e)
        where = f"episode {e} ({metric})"
        failed_prev: frozenset[str] = frozenset()
        for k in range(1, engine.scans + 1):
            st = rec.status.get((e, k))
            if st is None:
                if k <= last:
                    diffs.add(
                        "status",
                        f"{where}: no Status of scan {k} recorded (scans up to {last} are); "
                        f"the replay of this episode stops at scan {k - 1}",
                    )
                break
            at = f"{where} scan {k}"
            failed = frozenset(st.failed)
            engine.failures(failure_events(failed_prev, failed, k))
            failed_prev = failed
            plan = engine.decide(k, engine.unavailable(failed))
            if plan.enabled != st.enabled:
                diffs.add(
                    "allocation",
                    f"{at}: replayed allocation {list(plan.enabled)} != recorded "
                    f"{list(st.enabled)}",
                )
            elif float(plan.value) != st.value:
                diffs.add(
                    "value",
                    f"{at}: replayed objective {float(plan.value)!r} != recorded {st.value!r}",
                )
            _check_command(at, rec.commands.get((e, k)), plan, diffs)
            got: dict[str, Any] = {}
            for sid in st.fused:  # the first one recorded that the manager's test passes
                m = next((c for c in rec.candidates(e, k, sid) if engine.usable(c)), None)
                if m is None or sid not in ids:
                    diffs.add(
                        "measurement",
                        f"{at}: the manager fused {sid} but no valid measurement of it is recorded",
                    )
                    continue
                got[sid] = m
            for token in st.refiltered or ():  # the late ones the manager re-filtered
                sid, _, scan = token.rpartition(":")
                m = rec.meas.get((e, int(scan), sid)) if scan.isdigit() else None
                if m is None or not engine.insert_late(m):
                    diffs.add(
                        "refiltered",
                        f"{at}: the manager re-filtered {token} but the replay cannot (no "
                        "valid recorded message, or not insertable)",
                    )
            out = engine.report(plan, engine.fuse(plan, got), got)
            if out.trace_P != st.trace_P:
                diffs.add(
                    "trace_P", f"{at}: replayed tr P {out.trace_P!r} != recorded {st.trace_P!r}"
                )
            _check_tracks(at, rec.tracks.get((e, k), []), out, diffs)
        if len(engine.result.episodes[metric].value) < engine.scans:
            completed = False
    result = engine.result
    result.completed = completed
    return result


def _check_command(at: str, cmd: msg.Command | None, plan: Plan, diffs: Differences) -> None:
    """The recorded Command against the replayed plan: each sensor's target and clutter
    window (the enabled set is the Status's check)."""
    if cmd is None:
        return
    replayed = msg.Command(plan.k, 0.0, plan.enabled, 0, windows=plan.windows)
    if cmd.targets != plan.targets or replayed != msg.Command(
        plan.k, 0.0, plan.enabled, 0, windows=cmd.windows
    ):
        diffs.add(
            "command",
            f"{at}: the replayed targets or clutter windows are not the recorded Command's",
        )


def _check_tracks(at: str, recorded: list[msg.Track], out: Outcome, diffs: Differences) -> None:
    """Each replayed estimate against the first recorded Track of its target, bit for bit."""
    first = {tr.target_id: tr for tr in recorded[::-1]}
    for tid, g in out.tracks:
        tr = first.get(tid)
        if tr is None or (np.array_equal(tr.x, g.x) and np.array_equal(tr.P, g.P)):
            continue
        dx = float(np.max(np.abs(tr.x - g.x))) if tr.x.shape == g.x.shape else float("nan")
        what = "replayed estimate" if tid is None else f"the replayed estimate of {tid}"
        diffs.add("track", f"{at}: {what} differs from the recorded Track (max |dx| = {dx:.6g})")
