"""The recorder's loop: write every publication of the run to the recording as it arrives.

It subscribes to ``covnet/<run>/**`` *before* declaring its liveliness token, and the manager
waits for that token before its first command, so the recording misses nothing of the scan
loop.  Every sample is written as received (:class:`covnet.runs.recording.RecordingWriter`), also
when its payload does not decode.  The recorder does not decode strictly (the replay does, and
skips what does not): it reads each payload's kind and ``t_sent_ns`` with one plain msgpack
unpack (:func:`covnet.runs.recording.peek`, a tenth of a strict decode) and counts a payload that is
not a map of a known kind and schema version as ``undecodable:<reason>``.  It is not on the
scan loop's critical path, so it drains its queue in bursts: after a message arrives it waits
:data:`BATCH_S` and then writes everything queued (every sample keeps the receive stamp its
transport thread gave it), one wake-up per burst instead of one per message.  Like the world
and the sensors it sends a heartbeat every ``network.heartbeat_s`` (``scan``: the last
commanded scan it recorded).

It ends when ``stop`` is set or when the manager it has seen leaves (the run is over), and then
winds down: it keeps recording until nothing has arrived for :data:`QUIET_S` (messages still in
flight: zenoh may deliver the manager's token loss before its last data) and, when stopped by
a signal while the manager is still up, for up to ``linger_s`` so that the manager's last scan
lands in the recording too.  The caller closes the writer.

With a :class:`covnet.runs.visual.Visualiser` it also writes the visual channels (what Foxglove
draws: a scene, the numbers and a log line per scan) into the same file: after the run, from
what it recorded (:func:`draw_recording`), so that drawing costs the scan loop nothing; with
``--foxglove`` it also draws while the run goes, for the live view, at most
:data:`LIVE_MAX_HZ` scans a second (:class:`_LiveFeed`).  An error there is counted and never
stops the recording.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import Counter
from typing import Any

from covnet.clock import Clock
from covnet.config import Networked
from covnet.processes.node_kit import (
    NOTE,
    Heartbeat,
    ManagerWatch,
    config_id,
    manager_appear_s,
)
from covnet.runs.recording import RecordingReader, RecordingWriter, peek
from covnet.runs.visual import Visualiser
from covnet.wire import messages as msg
from covnet.wire.bus import Bus, Sample, dropped
from covnet.wire.codec import episode_of
from covnet.wire.profiling import Stages, profiled

ROLE = NODE_ID = msg.RECORDER_ID
QUIET_S = 0.2
"""Wind-down: stop once nothing has arrived for this long."""
LINGER_S = 1.0
"""Wind-down: longest time to keep recording after the stop (while the manager is up)."""
BATCH_S = 0.005
"""After a message wakes the loop: how long to let the burst gather before writing it."""
OWN_CLOCK_S = 60.0
"""A message's ``t_sent_ns`` is taken for a stamp of the recorder's clock (and is the
recording's ``publish_time``) only when it is at most this long before the message's receipt
and not after it: on one host ``CLOCK_MONOTONIC`` is shared and a message is received after it
was sent, within far less.  Another host's clock counts from its own boot (the hosts' uptimes
apart: hours, days), so its stamps land outside; the recording then gives the receive time as
``publish_time``, what MCAP asks for a message whose publish time is not known (the payload
keeps its stamp).  Two hosts booted within a minute of each other are not told apart."""
DRAW_BUDGET_S = 6.0
"""After the run: the longest time spent drawing the recording's visual channels (the launcher
stops a recorder 10 s after the manager at the latest; ~0.5 ms a scan: about 10 000 scans)."""
LIVE_MAX_HZ = 10.0
"""``--foxglove``: at most this many scans a second are drawn live (the latest one each time;
a lockstep run makes hundreds a second, which nobody could watch).  At 30 a second the live
view cost a lockstep paper run 16 % of its scans/s on 2 cores; at 10, nothing measurable
(README, "Seeing the network")."""


def _warn(counts: Counter[str], exc: Exception) -> None:
    counts["visual_errors"] += 1
    if counts["visual_errors"] == 1:
        print(f"recorder: visual channels: {type(exc).__name__}: {exc}", file=sys.stderr)


def draw_recording(
    writer: RecordingWriter, visualiser: Visualiser, counts: Counter[str], budget_s: float
) -> None:
    """Write the visual channels of what ``writer`` recorded (read back from its own file,
    flushed: the raw channels only) into it, scan by scan, for at most ``budget_s`` seconds
    (then say how far it got).  An error is counted and ends the drawing, never the recording;
    an ``OSError`` (the recording itself could not be written or read back) is raised."""
    deadline = time.monotonic() + budget_s
    try:
        samples = list(RecordingReader(writer.path).samples())
        for s in samples:
            if time.monotonic() > deadline:
                counts["visual_cut"] += 1
                print(
                    f"{NOTE}the recording's visual channels (Foxglove) hold the first "
                    f"{visualiser.frames} scans only: drawing them stopped at its "
                    f"{budget_s:.0f} s budget after the run (the raw channels hold every scan)",
                    file=sys.stderr,
                    flush=True,
                )
                break
            kind, t_sent, _ = peek(s.payload)
            out = visualiser.feed(kind, s.key, s.payload, s.t_recv_ns, t_sent)
            for vm in out:
                writer.write_visual(vm)
            counts["visual"] += len(out)
    except OSError:  # the recording's file could not be written (a full disk): not the picture's
        raise
    except Exception as exc:  # the picture must never cost the recording
        _warn(counts, exc)


class _LiveFeed:
    """``--foxglove``: the scans drawn while the run goes, at most :data:`LIVE_MAX_HZ` a second.
    A scan's command, measurements and tracks are kept raw until its Status; only a scan that
    is drawn is decoded (the truth always is: it may come once for the whole run)."""

    def __init__(self, visualiser: Visualiser | None, live: Any, counts: Counter[str]) -> None:
        assert visualiser is not None
        self.visualiser, self.live, self.counts = visualiser, live, counts
        self.pending: list[tuple[str, str, bytes, int, int | None]] = []
        self.next_ns = 0

    def add(self, kind: str, key: str, payload: bytes, t_recv: int, t_sent: int | None) -> None:
        try:
            if kind in (msg.Truth.KIND, msg.Heartbeat.KIND):  # (a heartbeat: its node's host)
                self.visualiser.feed(kind, key, payload, t_recv, t_sent)
            elif kind == msg.Status.KIND:
                now = time.monotonic_ns()
                if now >= self.next_ns:
                    self.next_ns = now + int(1e9 / LIVE_MAX_HZ)
                    for args in self.pending:
                        self.visualiser.feed(*args)
                    out = self.visualiser.feed(kind, key, payload, t_recv, t_sent)
                    for vm in out:
                        self.live.send(vm)
                    self.counts["live"] += len(out)
                self.pending.clear()
            elif kind in (msg.Command.KIND, msg.Measurement.KIND, msg.Track.KIND):
                self.pending.append((kind, key, payload, t_recv, t_sent))
        except Exception as exc:  # the picture must never cost the recording
            _warn(self.counts, exc)


def run(
    sc: Networked,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    writer: RecordingWriter,
    *,
    linger_s: float = LINGER_S,
    visualiser: Visualiser | None = None,
    live: Any = None,
    live_visualiser: Visualiser | None = None,
    draw_budget_s: float = DRAW_BUDGET_S,
) -> Counter[str]:
    """Record until the run is over (see module doc); returns counters: ``recorded``,
    ``undecodable:<reason>`` and ``kind:<kind>`` per message kind recorded; with a
    ``visualiser``, ``visual`` (visual messages written into the recording after the run:
    :func:`draw_recording`) and ``visual_errors``; with ``live`` (a
    :class:`covnet.runs.live.LiveView`) and its ``live_visualiser``, ``live`` (visual messages
    sent while the run went: :class:`_LiveFeed`)."""
    stages = Stages()  # the recorder's CPU (covnet bench up --profile; off by default)
    with profiled("recorder"):
        out = _run(
            sc, bus, run_id, clock, stop, writer, linger_s=linger_s, visualiser=visualiser,
            live=live, live_visualiser=live_visualiser, draw_budget_s=draw_budget_s,
            stages=stages,
        )  # fmt: skip
    stages.dump("recorder", recorded=out["recorded"])
    return out


def _run(
    sc: Networked,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    writer: RecordingWriter,
    *,
    linger_s: float,
    visualiser: Visualiser | None,
    live: Any,
    live_visualiser: Visualiser | None,
    draw_budget_s: float,
    stages: Stages | None = None,
) -> Counter[str]:
    lap = (stages if stages is not None else Stages()).lap
    counts: Counter[str] = Counter()
    sub = getattr(bus, "subscribe_stamped", bus.subscribe)(msg.run_keyexpr(run_id))
    # no grace: the recorder runs beside the manager (its router), and a manager gone without
    # its end is a crash whose recording the launcher rebuilds from at once
    manager = ManagerWatch(bus, run_id, appear_s=manager_appear_s(sc.network))
    token = bus.declare_token(msg.alive_key(run_id, ROLE, NODE_ID))
    heartbeat = Heartbeat(
        bus, clock, run_id, ROLE, NODE_ID, sc.network.heartbeat_s, config_id(sc)
    )
    last_scan = 0

    write = writer.write
    cmd_kind = msg.Command.KIND

    visual_counts: Counter[str] = Counter()
    feed = _LiveFeed(live_visualiser, live, visual_counts) if live is not None else None

    rejected: Counter[str] = Counter()  # what it could not decode, a Status said twice

    def rejections() -> Counter[str]:
        """By reason: the payloads that are no message (recorded all the same), a second Status
        of one key, episode and scan (``repeated_status``: a forged one, or the manager's after
        a forged one; the replay takes the first), and what its bus dropped before it saw it
        (oversized); in every heartbeat, so the manager's ``network.json`` counts them under
        the recorder (``rejected_by_node``)."""
        out = Counter(rejected)
        for reasons in dropped(bus).values():
            out.update(reasons)
        return out

    statuses: set[tuple[str, int | None, int | None]] = set()  # (key, episode, scan) heard
    status_kind = msg.Status.KIND
    own_clock_ns = int(OWN_CLOCK_S * 1e9)

    def record(s: Sample) -> None:
        nonlocal last_scan
        kind, t_sent, scan = peek(s.payload)
        t_pub = t_sent
        if t_sent is not None and not 0 <= s.t_recv_ns - t_sent <= own_clock_ns:
            t_pub = None  # not a stamp of this clock (OWN_CLOCK_S): the receive time
        if not write(s.key, s.payload, s.t_recv_ns, t_pub):
            rejected["no_channel"] += 1  # a new key with no channel left (writer.write)
            return
        counts[kind] += 1
        if kind.startswith("undecodable:"):
            rejected[kind.removeprefix("undecodable:")] += 1
        elif kind == status_kind:  # one Status per key, episode and scan: more is not the run's
            tag = (s.key, episode_of(s.payload), scan)
            if tag in statuses:
                rejected["repeated_status"] += 1
            statuses.add(tag)
        if kind == cmd_kind and scan is not None:
            last_scan = scan
        if feed is not None:
            feed.add(kind, s.key, s.payload, s.t_recv_ns, t_sent)

    try:
        now_ns = clock.now_ns
        while not stop.is_set():
            if now_ns() >= heartbeat.due_ns:  # the rejections counted only when one is due
                heartbeat.tick(last_scan, rejections())
            lap("heartbeat")
            s = sub.recv(timeout=sc.network.heartbeat_s / 2)
            lap("wait")
            if s is not None:
                time.sleep(BATCH_S)  # let the burst gather: one wake-up for all of it
                lap("wait: the burst")
                while s is not None:
                    record(s)
                    s = sub.try_recv()
                lap("record (peek, count, write)")
            writer.maybe_flush()
            lap("flush")
            if manager.left:
                break  # the manager left: the run is over
        # wind down: what is in flight, and the manager's last scan when stopped by a signal
        deadline = time.monotonic() + linger_s
        while (remaining := deadline - time.monotonic()) > 0:
            s = sub.recv(timeout=min(QUIET_S, remaining))
            manager.poll()
            if s is not None:
                record(s)
            elif not manager.up:
                break
        # the last word: every rejection to the end (the manager's linger waits for our token
        # to go, and reads this heartbeat sent before it)
        heartbeat.tick(last_scan, rejections(), now=True)
    finally:
        token.undeclare()
        sub.close()
        manager.close()
    writer.flush()
    if visualiser is not None:
        draw_recording(writer, visualiser, visual_counts, draw_budget_s)
    out: Counter[str] = Counter()
    for kind, n in counts.items():
        out[kind if kind.startswith("undecodable:") else f"kind:{kind}"] += n
    out["recorded"] = counts.total()
    out.update(visual_counts)
    return out
