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
in that instant).

**Peer mode** (no centre) is replayed node by node: for every node ``n`` with recorded
Statuses (its ``peer/<n>/status`` and ``peer/<n>/track`` keys) an engine of that node alone
(``ScanEngine(..., nodes=(n,))``, as the node's process stepped it) is stepped with the node's
Status (``failed``: the members it excluded; ``fused``: the local tracks it heard, taken from
the sensors' measurement keys); the decision must be the Status's, the fused estimate the
node's recorded Track bit for bit.  The run directory is written by the observer's own writer
(:func:`covnet.covariance_control.peer_run.write_peer_run`).
The steps shared by every kind's replay (reading the recording, the metadata check, the notes,
the byte-for-byte comparison, ``covnet replay`` itself) are :mod:`covnet.runs.replay_kit`'s.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from covnet.covariance_control.centre import ManagerResult
from covnet.covariance_control.config import KIND, Scenario
from covnet.covariance_control.engine import Outcome, Plan, ScanEngine
from covnet.covariance_control.model import build_model
from covnet.covariance_control.peer_run import NodeLog, PeerResult, write_peer_run
from covnet.covariance_control.results import write_network_run
from covnet.processes.runtime_stats import NetStats
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

    def load(self, cfg: Scenario, samples: Iterator[RecordedSample], run_id: str) -> Recorded:
        """The Status, Tracks, Commands and the sensors' messages the manager would accept
        (the engine's content test, bar the scan's own plan): measurements, or under a track
        rule local tracks; in peer mode also every node's Statuses and Tracks."""
        engine = ScanEngine(cfg, ["load"])
        engine.start_episode(0)
        if engine.peer:
            return _load_peer(samples, run_id, engine)
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
    ) -> ManagerResult | PeerResult:
        if isinstance(rec, PeerRecorded):
            return _recompute_peer(cfg, episodes, rec, diffs)
        return _recompute(cfg, episodes, rec, diffs)

    def write(
        self,
        out: Path,
        cfg: Scenario,
        result: ManagerResult | PeerResult,
        run_info: dict[str, Any],
    ) -> None:
        if isinstance(result, PeerResult):
            write_peer_run(out, cfg, result, run_info)
        else:
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


# --------------------------------------------------------------------------------------------
# peer mode: node by node
# --------------------------------------------------------------------------------------------


@dataclass
class PeerRecorded(Recorded):
    """A peer-mode recording: the sensors' local tracks (``meas``, ``others``) and every
    node's Statuses and Tracks, keyed by ``(node, episode, scan)`` (the first one received)."""

    node_status: dict[tuple[str, int, int], msg.Status] = field(default_factory=dict)
    node_track: dict[tuple[str, int, int], msg.Track] = field(default_factory=dict)


def _load_peer(samples: Iterator[RecordedSample], run_id: str, engine: ScanEngine) -> PeerRecorded:
    """The local tracks the nodes would accept and the nodes' own reports (strictly: a payload
    that does not decode, or whose ``node_id`` is not its key's, is counted and skipped)."""
    rest: list[RecordedSample] = []
    node_keys: list[tuple[str, str, RecordedSample]] = []
    for s in samples:
        try:
            node, what = msg.parse_peer_key(s.key)
        except ValueError:
            rest.append(s)
            continue
        node_keys.append((node, what, s))
    base = load_recording(
        iter(rest), run_id, message=msg.LocalTrack, label="local_track", acceptable=engine.usable
    )
    rec = PeerRecorded(**{f: getattr(base, f) for f in Recorded.__dataclass_fields__})
    for node, what, s in node_keys:
        rec.count("samples")
        try:
            m: msg.Status | msg.Track = (
                msg.decode_as(s.payload, msg.Status)
                if what == "status"
                else msg.decode_as(s.payload, msg.Track)
            )
        except msg.WireError as exc:
            rec.count(f"skipped:{exc.reason}")
            continue
        if m.node_id != node:
            rec.count("skipped:key_mismatch")
            continue
        rec.count(f"node_{what}")
        table: dict[tuple[str, int, int], Any] = (
            rec.node_status if what == "status" else rec.node_track
        )
        table.setdefault((node, m.episode, m.scan), m)
    return rec


def _recompute_peer(
    sc: Scenario, metrics: list[str], rec: PeerRecorded, diffs: Differences
) -> PeerResult:
    """Every recorded node's reports, recomputed by an engine of that node alone (module
    docstring)."""
    result = PeerResult(list(metrics), {}, NetStats())
    model = build_model(sc)
    completed = True
    for e, metric in enumerate(metrics):
        logs: dict[str, NodeLog] = {}
        nodes = sorted({n for (n, ep, _) in rec.node_status if ep == e})
        for node in nodes:
            log = _replay_node(sc, model, node, e, metric, rec, diffs)
            if log.statuses:
                logs[node] = log
        result.nodes[e] = logs
        full = [n for n, log in logs.items() if log.scans() == model.scans]
        completed = completed and bool(full)
    result.completed = completed
    return result


def _replay_node(
    sc: Scenario,
    model: Any,
    node: str,
    e: int,
    metric: str,
    rec: PeerRecorded,
    diffs: Differences,
) -> NodeLog:
    """Node ``node``'s episode ``e``: its engine stepped with its recorded Statuses."""
    if node not in model.sensor_ids:
        diffs.add("status", f"episode {e}: Statuses of {node!r}, which is not a sensor")
        return NodeLog()
    engine = ScanEngine(sc, [metric], model=model, nodes=(model.sensor_ids.index(node),))
    engine.start_episode(0)
    log = NodeLog()
    for k in range(1, engine.scans + 1):
        st = rec.node_status.get((node, e, k))
        if st is None:
            break
        at = f"episode {e} ({metric}) node {node} scan {k}"
        plan = engine.decide(k, engine.unavailable(frozenset(st.failed)))
        if plan.enabled != st.enabled:
            diffs.add(
                "allocation",
                f"{at}: replayed allocation {list(plan.enabled)} != recorded {list(st.enabled)}",
            )
        elif float(plan.value) != st.value:
            diffs.add("value", f"{at}: replayed objective {plan.value!r} != recorded {st.value!r}")
        got: dict[str, Any] = {}
        for sid in st.fused:
            m = next((c for c in rec.candidates(e, k, sid) if engine.usable(c)), None)
            if m is None:
                diffs.add("measurement", f"{at}: {node} fused {sid}'s track but none is recorded")
                continue
            got[sid] = m
        out = engine.report(plan, engine.fuse(plan, got), got)
        if out.trace_P != st.trace_P:
            diffs.add("trace_P", f"{at}: replayed tr P {out.trace_P!r} != recorded {st.trace_P!r}")
        est = out.tracks[0][1]
        tr = rec.node_track.get((node, e, k))
        if tr is not None and not (np.array_equal(tr.x, est.x) and np.array_equal(tr.P, est.P)):
            diffs.add("track", f"{at}: the replayed estimate differs from the node's Track")
        log.add(
            msg.Status(
                scan=k,
                t=st.t,
                enabled=plan.enabled,
                trace_P=out.trace_P,
                trace_Pd=out.trace_Pd,
                value=out.value,
                t_sent_ns=0,
                episode=e,
                fused=out.fused,
                failed=st.failed,
                node_id=node,
            )
        )
        log.add(msg.Track(scan=k, t=st.t, x=est.x, P=est.P, t_sent_ns=0, episode=e, node_id=node))
    return log
