"""The world's loop: publish ``Truth(k)`` for every scan the manager commands.

The trajectory is a pure function of the scenario and its seed
(:func:`covnet.model.truth_trajectory`); the world advances on the manager's scan tick, in
lockstep and in real time alike: on ``Command(k)`` it publishes ``Truth(k)`` (unless already
sent) and ``Truth(k+1)`` ahead, so that an enabled sensor usually holds the truth when its next
command arrives (a sensor only measures a scan it was commanded for).  It ends on ``stop`` or
when the manager it has seen leaves.
"""

from __future__ import annotations

import threading
from collections import Counter

from covnet import messages as msg
from covnet.bus import Bus
from covnet.clock import Clock
from covnet.config import Scenario
from covnet.model import build_model, truth_trajectory

TARGET_IDS = ("T1",)


def run(sc: Scenario, bus: Bus, run_id: str, clock: Clock, stop: threading.Event) -> Counter[str]:
    """Serve truth until ``stop`` is set; returns counters (``published``, and
    ``rejected:<reason>`` for every malformed or out-of-range command dropped)."""
    model = build_model(sc)
    truth = truth_trajectory(model)
    counts: Counter[str] = Counter()
    cmd_sub = bus.subscribe(msg.command_key(run_id))
    manager_watch = bus.watch_liveliness(msg.alive_key(run_id, "manager", "manager"))
    manager_seen = False
    token = bus.declare_token(msg.alive_key(run_id, "world", "world"))
    key = msg.truth_key(run_id)
    hb_key = msg.heartbeat_key(run_id, "world", "world")
    hb_period_ns = int(sc.network.heartbeat_s * 1e9)
    next_hb = 0
    last_scan = 0
    published: set[int] = set()  # scans whose truth went out since the last command
    try:
        while not stop.is_set():
            while (ev := manager_watch.try_recv()) is not None:
                manager_seen = manager_seen or ev.alive
                if manager_seen and not ev.alive:
                    stop.set()  # the manager left: the run is over
            now = clock.now_ns()
            if now >= next_hb:
                rejected = {
                    k.split(":", 1)[1]: v for k, v in counts.items() if k.startswith("rejected:")
                }
                hb = msg.Heartbeat(
                    role="world",
                    node_id="world",
                    scan=last_scan,
                    t_sent_ns=now,
                    rejected=rejected or None,
                )
                bus.publish(hb_key, msg.encode(hb))
                next_hb = now + hb_period_ns
            s = cmd_sub.recv(timeout=sc.network.heartbeat_s / 2)
            if s is None:
                continue
            try:
                cmd = msg.decode_as(s.payload, msg.Command)
            except msg.WireError as exc:
                counts[f"rejected:{exc.reason}"] += 1
                continue
            if not 1 <= cmd.scan <= model.scans:
                counts["rejected:bad_scan"] += 1
                continue
            last_scan = cmd.scan
            # scan k now, and k+1 ahead of its command: the sensors then have the truth in
            # hand when the next command comes (one bus hop less on the scan's critical path)
            for k in (cmd.scan, cmd.scan + 1):
                if k <= model.scans and k not in published:
                    tr = msg.Truth(
                        scan=k, t=k * model.T, target_ids=TARGET_IDS, states=truth[k - 1][None, :]
                    )
                    bus.publish(key, msg.encode(tr))
                    counts["published"] += 1
            published = {cmd.scan, cmd.scan + 1}
    finally:
        token.undeclare()
    return counts
