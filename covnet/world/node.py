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
from covnet.node_kit import serve_commands

TARGET_IDS = ("T1",)


def run(sc: Scenario, bus: Bus, run_id: str, clock: Clock, stop: threading.Event) -> Counter[str]:
    """Serve truth until ``stop`` is set; returns counters (``published``, and
    ``rejected:<reason>`` for every malformed or out-of-range command dropped)."""
    model = build_model(sc)
    truth = truth_trajectory(model)
    counts: Counter[str] = Counter()
    key = msg.truth_key(run_id)
    published: set[int] = set()  # scans whose truth went out since the last command

    def handle(cmd: msg.Command) -> bool:
        nonlocal published
        if not 1 <= cmd.scan <= model.scans:
            counts["rejected:bad_scan"] += 1
            return False
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
        return True

    serve_commands(bus, run_id, clock, stop, sc.network, "world", "world", counts, handle)
    return counts
