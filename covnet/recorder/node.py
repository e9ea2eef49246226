"""The recorder's loop: write every publication of the run to the recording as it arrives.

It subscribes to ``covnet/<run>/**`` *before* declaring its liveliness token, and the manager
waits for that token before its first command, so the recording misses nothing of the scan
loop.  Every sample is written as received (:class:`covnet.recording.RecordingWriter`), also
when its payload does not decode (counted as ``undecodable:<reason>``: the replay decodes
strictly and skips it).  Like the world and the sensors it sends a heartbeat every
``network.heartbeat_s`` (``scan``: the last commanded scan it recorded).

It ends when ``stop`` is set or when the manager it has seen leaves (the run is over), and then
winds down: it keeps recording until nothing has arrived for :data:`QUIET_S` (messages still in
flight: zenoh may deliver the manager's token loss before its last data) and, when stopped by
a signal while the manager is still up, for up to ``linger_s`` so that the manager's last scan
lands in the recording too.  The caller closes the writer.
"""

from __future__ import annotations

import threading
import time
from collections import Counter

from covnet import messages as msg
from covnet.bus import Bus, Sample
from covnet.clock import Clock
from covnet.config import Scenario
from covnet.node_kit import Heartbeat, ManagerWatch
from covnet.recording import RecordingWriter

ROLE = NODE_ID = "recorder"
QUIET_S = 0.2
"""Wind-down: stop once nothing has arrived for this long."""
LINGER_S = 1.0
"""Wind-down: longest time to keep recording after the stop (while the manager is up)."""


def run(
    sc: Scenario,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    writer: RecordingWriter,
    *,
    linger_s: float = LINGER_S,
) -> Counter[str]:
    """Record until the run is over (see module doc); returns counters: ``recorded``,
    ``undecodable:<reason>`` and ``kind:<kind>`` per message kind recorded."""
    counts: Counter[str] = Counter()
    sub = bus.subscribe(msg.run_keyexpr(run_id))
    manager = ManagerWatch(bus, run_id)
    token = bus.declare_token(msg.alive_key(run_id, ROLE, NODE_ID))
    heartbeat = Heartbeat(bus, clock, run_id, ROLE, NODE_ID, sc.network.heartbeat_s)
    last_scan = 0

    def record(s: Sample) -> None:
        nonlocal last_scan
        t_sent: int | None = None
        try:
            m = msg.decode(s.payload)
        except msg.WireError as exc:
            counts[f"undecodable:{exc.reason}"] += 1
        else:
            counts[f"kind:{m.KIND}"] += 1
            t_sent = getattr(m, "t_sent_ns", None)
            if isinstance(m, msg.Command):
                last_scan = m.scan
        writer.write(s.key, s.payload, s.t_recv_ns, t_sent)
        counts["recorded"] += 1

    try:
        while not stop.is_set():
            heartbeat.tick(last_scan)
            s = sub.recv(timeout=sc.network.heartbeat_s / 2)
            while s is not None:
                record(s)
                s = sub.try_recv()
            writer.maybe_flush()
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
    finally:
        token.undeclare()
        sub.close()
        manager.close()
    writer.flush()
    return counts
