"""A mobile sensor: measure only the commanded targets, from the world's truth geometry.

Per ``Command(k)`` that lists this sensor in ``enabled`` it waits for ``Truth(k)`` (the targets'
true states and its own platform's position and velocity after this scan's move), draws each
commanded target's detection and noise with :func:`covnet.mobile.model.measure_pair` (stream
``[seed, 3, k, i, j]``: the draw ``covnet run`` makes) and publishes one ``Measurement(k)``:
the detections (``z`` with their ``target_ids``; possibly none) and its ``platform`` state.
A command whose truth never comes is dropped once a newer one arrives.  Heartbeats, liveliness
and the end of the run as for the covariance-control sensor (:mod:`sensors.node`).
"""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

from covnet import messages as msg
from covnet.bus import Bus, Sample
from covnet.clock import Clock
from covnet.mobile.config import MobileConfig
from covnet.mobile.model import build_model, measure_pair
from sensors.node import SensorStats


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
    stats = SensorStats()
    cmd_sub = bus.subscribe(msg.command_key(run_id))
    truth_sub = bus.subscribe(msg.truth_key(run_id))
    manager_watch = bus.watch_liveliness(msg.alive_key(run_id, "manager", "manager"))
    manager_seen = False
    token = bus.declare_token(msg.alive_key(run_id, "sensor", sensor_id))
    meas_key = msg.measurement_key(run_id, sensor_id)
    hb_key = msg.heartbeat_key(run_id, "sensor", sensor_id)
    hb_period_ns = int(cfg.network.heartbeat_s * 1e9)
    truths: dict[int, msg.Truth] = {}
    pending: deque[msg.Command] = deque()
    last_scan = 0
    next_hb = 0

    def heartbeat() -> None:
        nonlocal next_hb
        now = clock.now_ns()
        if now >= next_hb:
            hb = msg.Heartbeat(
                role="sensor",
                node_id=sensor_id,
                scan=last_scan,
                t_sent_ns=now,
                rejected=dict(stats.rejected) or None,
            )
            bus.publish(hb_key, msg.encode(hb))
            next_hb = now + hb_period_ns

    def accept(s: Sample | None) -> bool:
        nonlocal last_scan
        if s is None:
            return False
        try:
            cmd = msg.decode_as(s.payload, msg.Command)
        except msg.WireError as exc:
            stats.rejected[exc.reason] += 1
            return True
        stats.commands += 1
        last_scan = cmd.scan
        if sensor_id in cmd.enabled:
            stats.enabled_scans += 1
            pending.append(cmd)
        return True

    def take_truth(timeout: float | None) -> bool:
        s = truth_sub.recv(timeout) if timeout is not None else truth_sub.try_recv()
        if s is None:
            return False
        try:
            tr = msg.decode_as(s.payload, msg.Truth)
        except msg.WireError as exc:
            stats.rejected[exc.reason] += 1
            return True
        if (
            tr.platforms is None
            or tr.sensor_ids is None
            or sensor_id not in tr.sensor_ids
            or tr.states.shape[1] != 4
        ):
            stats.rejected["bad_shape"] += 1
            return True
        truths[tr.scan] = tr
        for old in [s for s in truths if s < tr.scan - 2]:  # scans this sensor was not in
            del truths[old]
        return True

    def publish_measurement(cmd: msg.Command) -> None:
        k = cmd.scan
        tr = truths[k]
        assert tr.sensor_ids is not None and tr.platforms is not None
        row = tr.platforms[tr.sensor_ids.index(sensor_id)]
        q, qdot = np.array(row[:2]), np.array(row[2:])
        zs: list[np.ndarray] = []
        ids: list[str] = []
        for tid in (cmd.targets or {}).get(sensor_id, ()):
            if tid not in tindex or tid not in tr.target_ids:
                stats.rejected["bad_target"] += 1
                continue
            x_true = np.array(tr.states[tr.target_ids.index(tid)])
            hit, z, _ = measure_pair(model, k, tindex[tid], j, x_true, q, qdot)
            if hit:
                zs.append(z)
                ids.append(tid)
        m = msg.Measurement(
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
        bus.publish(meas_key, msg.encode(m))
        stats.measurements_sent += 1
        for old in [s for s in truths if s < k]:
            del truths[old]

    def manager_left() -> bool:
        nonlocal manager_seen
        while (ev := manager_watch.try_recv()) is not None:
            if ev.alive:
                manager_seen = True
            elif manager_seen:
                return True
        return False

    try:
        while not stop.is_set():
            heartbeat()
            if manager_left():
                break
            if pending:
                take_truth(cfg.network.heartbeat_s / 2)
            else:
                accept(cmd_sub.recv(timeout=cfg.network.heartbeat_s / 2))
            while accept(cmd_sub.try_recv()):
                pass
            while take_truth(None):
                pass
            while pending:
                cmd = pending[0]
                if cmd.scan in truths:
                    publish_measurement(cmd)
                elif len(pending) > 1:
                    stats.missed_truth += 1
                else:
                    break
                pending.popleft()
    finally:
        token.undeclare()
    return stats
