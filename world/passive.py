"""The passive world: on ``Command(k)`` it publishes ``Truth(k)``, the true target positions
``(N, 3)`` km (the targets are static: the configured formation).  A repeated command is
ignored; anything malformed or out of order is counted by reason and dropped.  It ends on
``stop`` or when the manager leaves."""

from __future__ import annotations

import threading
from collections import Counter

from covnet.clock import Clock
from covnet.passive.config import PassiveConfig
from covnet.processes.node_kit import config_id, serve_commands
from covnet.wire import messages as msg
from covnet.wire.bus import Bus

ROLE = NODE_ID = "world"


def target_ids(n: int) -> tuple[str, ...]:
    """``T1 … Tn``: the paper's numbering."""
    return tuple(f"T{i + 1}" for i in range(n))


def run(
    cfg: PassiveConfig, bus: Bus, run_id: str, clock: Clock, stop: threading.Event
) -> Counter[str]:
    """Serve truth until ``stop`` is set; returns counters: ``published``, ``duplicate``,
    ``rejected:<reason>``."""
    targets = cfg.scene_model().targets
    ids = target_ids(len(targets))
    counts: Counter[str] = Counter()
    key = msg.truth_key(run_id)
    state = {"last": 0}

    def handle(cmd: msg.Command) -> bool:
        if cmd.scan == state["last"]:
            counts["duplicate"] += 1
            return False
        # any later scan of the run: the targets do not move, so a command that never came
        # (lost, or the world paused past its session's lease) leaves nothing to make up (one
        # missed command made the world refuse every later one: no truth to the run's end)
        if not state["last"] < cmd.scan <= cfg.scans:
            counts["rejected:bad_scan"] += 1
            return False
        k = cmd.scan
        bus.publish(key, msg.encode(msg.Truth(scan=k, t=float(k), target_ids=ids, states=targets)))
        counts["published"] += 1
        state["last"] = k
        return True

    serve_commands(
        bus, run_id, clock, stop, cfg.network, ROLE, NODE_ID, counts, handle,
        config=config_id(cfg),
    )  # fmt: skip
    return counts
