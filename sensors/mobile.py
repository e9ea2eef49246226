"""A mobile sensor: measure only the commanded targets, from the world's truth geometry.

Per ``Command(k)`` that lists this sensor in ``enabled`` it waits for ``Truth(k)`` (the targets'
true states and its own platform's position and velocity after this scan's move), draws each
commanded target's detection and noise with :func:`covnet.mobile.model.measure_pair` (stream
``[seed, 3, k, i, j]``: the draw ``covnet run`` makes) and publishes one ``Measurement(k)``:
the detections (``z`` with their ``target_ids``; possibly none) and its ``platform`` state.
The protocol (commands, truth, heartbeats, liveliness, a missed truth, the end of the run) is
the one every sensor shares, :func:`sensors.protocol.serve`; this module only says what a usable
truth is and how to measure.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from covnet.clock import Clock
from covnet.mobile.config import MobileConfig
from covnet.mobile.model import build_model, measure_pair
from covnet.processes.node_kit import config_id
from covnet.wire import messages as msg
from covnet.wire.bus import Bus
from sensors.protocol import SensorStats, process_main, serve


def run(
    cfg: MobileConfig,
    sensor_id: str,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
) -> SensorStats:
    """Serve commands until ``stop`` is set; returns this sensor's counters
    (``measurements_sent`` counts the Measurement messages, one per commanded scan)."""
    model = build_model(cfg)
    j = model.sensor_ids.index(sensor_id)
    R0 = model.sensors.R0[j]
    tindex = {tid: i for i, tid in enumerate(model.target_ids)}
    bad_targets = [0]

    def truth_ok(tr: msg.Truth) -> bool:
        return (
            tr.platforms is not None
            and tr.sensor_ids is not None
            and sensor_id in tr.sensor_ids
            and tr.states.shape[1] == 4
        )

    def respond(cmd: msg.Command, tr: msg.Truth) -> msg.Measurement:
        k = cmd.scan
        assert tr.sensor_ids is not None and tr.platforms is not None
        row = tr.platforms[tr.sensor_ids.index(sensor_id)]
        q, qdot = np.array(row[:2]), np.array(row[2:])
        zs: list[np.ndarray] = []
        ids: list[str] = []
        for tid in (cmd.targets or {}).get(sensor_id, ()):
            if tid not in tindex or tid not in tr.target_ids:
                bad_targets[0] += 1
                continue
            x_true = np.array(tr.states[tr.target_ids.index(tid)])
            hit, z, _ = measure_pair(model, k, tindex[tid], j, x_true, q, qdot)
            if hit:
                zs.append(z)
                ids.append(tid)
        return msg.Measurement(
            sensor_id=sensor_id,
            scan=k,
            t=cmd.t,
            z=np.array(zs) if zs else np.zeros((0, 2)),
            R=R0,
            t_sent_ns=clock.now_ns(),
            episode=cmd.episode,
            target_ids=tuple(ids),
            platform=row,
        )

    stats = serve(
        sensor_id, bus, run_id, clock, stop, cfg.network, truth_ok=truth_ok, respond=respond,
        scans=cfg.scans, config=config_id(cfg),
    )
    if bad_targets[0]:
        stats.rejected["bad_target"] += bad_targets[0]
    return stats


def main(args: Any, cfg: MobileConfig, stop: threading.Event) -> int:
    """``python -m sensors --config ... --id ID``: the process around :func:`run`."""
    return process_main(args, cfg, stop, run)
