"""The mobile world: targets on their true trajectories, platforms moved by their commanded modes.

On ``Command(k)`` (in scan order: ``k`` is the scan after the last one served) it moves every
platform by the mode the command gives it (a sensor absent from ``modes``, e.g. a failed one,
stays) with :func:`covnet.mobile.model.move_platforms`, and publishes ``Truth(k)``: the targets'
states (row ``k`` of :func:`covnet.mobile.model.truth`) and the platforms' positions and
velocities.  A repeated command is ignored; anything malformed, out of order or naming an
unknown mode is counted by reason and dropped.  It ends on ``stop`` or when the manager leaves.
"""

from __future__ import annotations

import threading
from collections import Counter

import numpy as np

from covnet.clock import Clock
from covnet.core.mobile.models import MODE_NAMES, STAY
from covnet.mobile.config import MobileConfig
from covnet.mobile.model import build_model, move_platforms, truth
from covnet.processes.node_kit import config_id, serve_commands
from covnet.wire import messages as msg
from covnet.wire.bus import Bus

ROLE = NODE_ID = "world"
MODE_INDEX = {name: i for i, name in enumerate(MODE_NAMES)}


def modes_of(cmd: msg.Command, sensor_ids: tuple[str, ...]) -> np.ndarray | None:
    """The mode index of every sensor commanded by ``cmd`` (absent: stay); None when a mode
    name is unknown."""
    given = cmd.modes or {}
    out = np.full(len(sensor_ids), STAY, dtype=np.intp)
    for j, sid in enumerate(sensor_ids):
        name = given.get(sid)
        if name is not None:
            if name not in MODE_INDEX:
                return None
            out[j] = MODE_INDEX[name]
    return out


def run(
    cfg: MobileConfig, bus: Bus, run_id: str, clock: Clock, stop: threading.Event
) -> Counter[str]:
    """Serve truth until ``stop`` is set; returns counters: ``published``, ``duplicate``,
    ``rejected:<reason>``."""
    model = build_model(cfg)
    X = truth(model)
    pos = model.sensors.position.copy()
    counts: Counter[str] = Counter()
    key = msg.truth_key(run_id)
    last = 0

    def handle(cmd: msg.Command) -> bool:
        nonlocal pos, last
        if cmd.scan == last:
            counts["duplicate"] += 1
            return False
        if cmd.scan != last + 1 or cmd.scan > model.scans:
            counts["rejected:bad_scan"] += 1
            return False
        modes = modes_of(cmd, model.sensor_ids)
        if modes is None:
            counts["rejected:bad_mode"] += 1
            return False
        k = cmd.scan
        pos, qdot = move_platforms(model, pos, modes)
        tr = msg.Truth(
            scan=k,
            t=k * model.T,
            target_ids=model.target_ids,
            states=X[k],
            sensor_ids=model.sensor_ids,
            platforms=np.hstack([pos, qdot]),
        )
        bus.publish(key, msg.encode(tr))
        counts["published"] += 1
        last = k
        return True

    serve_commands(
        bus, run_id, clock, stop, cfg.network, ROLE, NODE_ID, counts, handle,
        config=config_id(cfg),
    )  # fmt: skip
    return counts
