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

from covnet import messages as msg
from covnet.bus import Bus
from covnet.clock import Clock
from covnet.core.mobile.models import MODE_NAMES, STAY
from covnet.mobile.config import MobileConfig
from covnet.mobile.model import build_model, move_platforms, truth

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
    cmd_sub = bus.subscribe(msg.command_key(run_id))
    manager_watch = bus.watch_liveliness(msg.alive_key(run_id, "manager", "manager"))
    manager_seen = False
    token = bus.declare_token(msg.alive_key(run_id, ROLE, NODE_ID))
    key = msg.truth_key(run_id)
    hb_key = msg.heartbeat_key(run_id, ROLE, NODE_ID)
    hb_period_ns = int(cfg.network.heartbeat_s * 1e9)
    next_hb = 0
    last_scan = 0
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
                    role=ROLE,
                    node_id=NODE_ID,
                    scan=last_scan,
                    t_sent_ns=now,
                    rejected=rejected or None,
                )
                bus.publish(hb_key, msg.encode(hb))
                next_hb = now + hb_period_ns
            s = cmd_sub.recv(timeout=cfg.network.heartbeat_s / 2)
            if s is None:
                continue
            try:
                cmd = msg.decode_as(s.payload, msg.Command)
            except msg.WireError as exc:
                counts[f"rejected:{exc.reason}"] += 1
                continue
            if cmd.scan == last_scan:
                counts["duplicate"] += 1
                continue
            if cmd.scan != last_scan + 1 or cmd.scan > model.scans:
                counts["rejected:bad_scan"] += 1
                continue
            modes = modes_of(cmd, model.sensor_ids)
            if modes is None:
                counts["rejected:bad_mode"] += 1
                continue
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
            last_scan = k
    finally:
        token.undeclare()
    return counts
