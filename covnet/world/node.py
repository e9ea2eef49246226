"""The world's loop: publish ``Truth(k)`` for every scan the manager commands.

The trajectory is a pure function of the scenario and its seed
(:func:`covnet.model.truth_trajectory`); the world advances on the manager's scan tick (the
command), in lockstep and in real time alike, so sensors never measure a scan the world has
not reached.
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


def run(
    sc: Scenario, bus: Bus, run_id: str, clock: Clock, stop: threading.Event
) -> Counter[str]:
    """Serve truth until ``stop`` is set; returns counters (published, rejected reasons)."""
    model = build_model(sc)
    truth = truth_trajectory(model)
    counts: Counter[str] = Counter()
    cmd_sub = bus.subscribe(msg.command_key(run_id))
    token = bus.declare_token(msg.alive_key(run_id, "world", "world"))
    key = msg.truth_key(run_id)
    hb_key = msg.heartbeat_key(run_id, "world", "world")
    hb_period_ns = int(sc.network.heartbeat_s * 1e9)
    next_hb = 0
    last_scan = 0
    try:
        while not stop.is_set():
            now = clock.now_ns()
            if now >= next_hb:
                hb = msg.Heartbeat(role="world", node_id="world", scan=last_scan, t_sent_ns=now)
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
            tr = msg.Truth(
                scan=cmd.scan, t=cmd.t, target_ids=TARGET_IDS, states=truth[cmd.scan - 1][None, :]
            )
            bus.publish(key, msg.encode(tr))
            counts["published"] += 1
    finally:
        token.undeclare()
    return counts
