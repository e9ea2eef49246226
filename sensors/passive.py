"""A passive sensor: per enabled ``Command(k)`` and the world's ``Truth(k)`` (the target
positions), its list of (azimuth, elevation) pairs for scan ``k``, with missed detections and
clutter when the config enables them, published as one ``Measurement(k)``: ``z`` ``(n, 2)`` rad
(possibly ``n = 0``), ``R = diag(σ_α², σ_ε²)``.

The list is row ``j`` of :func:`covnet.passive.scene.draw` for trial ``k - 1`` with the truth's
positions.  Random streams: scan ``k`` (1-based) is trial ``k - 1`` of the scene draw, the one
generator ``default_rng([seed, k - 1])`` that ``covnet run`` (trial 0) and the Monte Carlo use.
Each sensor process draws that scan's whole scene from it (given the world's target positions)
and keeps only its own list: the draw order is fixed, so every process holds the identical
scene, the lists it publishes are exactly the ones the in-process run associates, and the Monte
Carlo's common random numbers stay as they are.  The price is drawing three lists instead of
one (microseconds).  The manager draws the same scene once more, for scoring only.  The
protocol (commands, truth, heartbeats, liveliness, a missed truth, the end of the run) is the
one every sensor shares, :func:`sensors.protocol.serve`.
"""

from __future__ import annotations

import threading
from dataclasses import replace
from typing import Any

import numpy as np

from covnet.clock import Clock
from covnet.passive.config import PassiveConfig
from covnet.passive.scene import draw
from covnet.processes.node_kit import config_id
from covnet.wire import messages as msg
from covnet.wire.bus import Bus
from sensors.protocol import SensorStats, process_main, serve


def run(
    cfg: PassiveConfig,
    sensor_id: str,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
) -> SensorStats:
    """Serve commands until ``stop`` is set; returns this sensor's counters."""
    model = cfg.scene_model()
    j = cfg.sensor_ids.index(sensor_id)
    R = np.diag([model.sigma_azimuth[j] ** 2, model.sigma_elevation[j] ** 2])
    n_targets = model.targets.shape[0]

    def truth_ok(tr: msg.Truth) -> bool:
        return tr.states.shape == (n_targets, 3)

    def respond(cmd: msg.Command, tr: msg.Truth) -> msg.Measurement:
        scene = draw(replace(model, targets=np.array(tr.states)), cfg.seed, cmd.scan - 1)
        return msg.Measurement(
            sensor_id=sensor_id,
            scan=cmd.scan,
            t=cmd.t,
            z=scene.scan.z[j],
            R=R,
            t_sent_ns=clock.now_ns(),
            episode=cmd.episode,
        )

    return serve(
        sensor_id, bus, run_id, clock, stop, cfg.network, truth_ok=truth_ok, respond=respond,
        scans=cfg.scans, config=config_id(cfg),
    )


def main(args: Any, cfg: PassiveConfig, stop: threading.Event) -> int:
    """``python -m sensors --config ... --id ID``: the process around :func:`run`."""
    return process_main(args, cfg, stop, run)
