"""A covariance-control sensor: measure the truth when commanded, publish the measurement.

Per ``Command(k)`` that enables it (the protocol every sensor shares,
:func:`sensors.protocol.serve`), it draws its measurement ``z = H x + v`` from its own noise
stream ``(seed, j, k)`` (:func:`covnet.covariance_control.model.measure`, the same draw
``covnet run`` makes) and publishes ``Measurement(k)``; under a fusion rule whose sensors run
local filters (``fusion.mode: info | ci``) it publishes its
:class:`~covnet.wire.messages.LocalTrack`
instead.  The measurement noise of the first scans is drawn at start-up (:class:`NoiseTable`):
that takes work off the scan's critical path and changes no result.  Its payload is then written
from the sensor's msgpack template (:func:`fast_respond`,
:class:`covnet.wire.batch_encode.MeasurementTemplate`: the codec's bytes, without building the
message; issue 29's seventh round).  With ``fusion.mode: peer`` the process is a peer node
instead (:mod:`sensors.peer`).

Many targets (a config with ``targets:``, :func:`run_targets`): a command that enables the
sensor names the target it dwells on and, for a sensor with clutter, the dwell's clutter
window; the sensor simulates its own model's returns from that target's truth
(:func:`covnet.covariance_control.targets.dwell`: detection with its ``pd`` inside its coverage,
Poisson clutter in the window, shuffled, from its noise stream ``(seed, j, k)``) and publishes
them unlabeled, ``z`` ``(m, dim_z)``; under ``fusion.mode: info`` its own filter's track of
that target instead (:class:`covnet.covariance_control.targets.LocalTargets`).  A command
that does not name one known target for it (or whose window is not one of its model's) is
rejected (``bad_value``) and not answered.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from covnet.clock import Clock, WallClock
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.model import Model, build_model, measure
from covnet.covariance_control.sensor_side import Measured, SensorSide, Tracked
from covnet.processes.node_kit import config_id, not_ended_well
from covnet.processes.process import EXIT_OK, EXIT_RUN_FAILED, open_client
from covnet.wire import messages as msg
from covnet.wire.batch_encode import MeasurementTemplate
from covnet.wire.bus import Bus
from covnet.wire.latency_bus import for_sensor
from sensors.host import say
from sensors.protocol import FastRespond, SensorStats, process_main, serve


def main(args: Any, sc: Scenario, stop: threading.Event) -> int:
    """``python -m sensors --config PAPER.yaml --id S3 ...``: a sensor (or, in peer mode, a
    peer node); ``network.latency`` emulated in this process in real time unless a real
    emulated path does it (``--no-app-latency``, set by ``covnet up --netns``)."""
    if not sc.fusion.has_centre:
        return _peer(args, sc, stop)
    wrap = None
    if args.realtime and not args.no_app_latency and not sc.network.latency.is_ideal(sc.sensor_ids):

        def wrap(bus: Bus) -> Any:
            return for_sensor(bus, sc, args.id, args.run, args.speed)

    return process_main(args, sc, stop, run, wrap)


def _peer(args: Any, sc: Scenario, stop: threading.Event) -> int:
    """``fusion.mode: peer``: this sensor is a peer node (decides and fuses with its
    neighbours); the episodes are the config's metrics."""
    from sensors import peer  # the allocator and the fusion: start-up of a measuring sensor

    if args.realtime:
        raise ValueError("--realtime: peer mode runs in lockstep only")
    with open_client(args, sc.network, "sensor", args.id, stop) as bus:
        stats = peer.run(
            sc, args.id, list(sc.allocation.metrics), bus, args.run, WallClock(args.speed), stop
        )
    say(
        args,
        f"stopped: {stats.scans} scans, {stats.tracks_sent} tracks sent, "
        f"{stats.tracks_fused} fused, rejected {dict(stats.rejected)}",
    )
    if stats.manager_lost:
        say(args, not_ended_well(args.run, "this peer node"))
        return EXIT_RUN_FAILED
    return EXIT_OK


def run_surveillance(
    sc: Scenario,
    sensor_id: str,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
) -> SensorStats:
    """A sensor of a surveillance scenario (``surveillance:``): a command that enables it
    names its mode (``K<id>``, a track, or ``C<c>``, a search cell) and its window; it
    returns every present target's measurement inside the window and its clutter
    (:func:`covnet.covariance_control.surveillance.dwell`, the draws ``covnet run`` makes),
    from the world's truth of the targets present at the scan."""
    # start-up: the surveillance world only for configs with surveillance
    from covnet.covariance_control import surveillance, targets

    sm = surveillance.build(sc)
    j = sm.sensor_ids.index(sensor_id)
    index = {tid: i for i, tid in enumerate(sm.truth_ids)}
    side = SensorSide.of_process(sc, sm, j)

    def truth_ok(tr: msg.Truth) -> bool:
        return all(t in index for t in tr.target_ids) and tr.states.shape == (
            len(tr.target_ids), 4,
        )  # fmt: skip

    def command_ok(cmd: msg.Command) -> bool:
        task = (cmd.targets or {}).get(sensor_id)
        if task is None or len(task) != 1 or not surveillance.is_task(task[0], sm.n_cells):
            return False
        v = (cmd.windows or {}).get(sensor_id)
        if v is None:
            return False
        try:
            targets.window_from_vec(sm.tm, j, v)
        except ValueError:
            return False
        return True

    def respond(cmd: msg.Command, tr: msg.Truth) -> msg.Measurement | msg.LocalTrack:
        win = targets.window_from_vec(sm.tm, j, (cmd.windows or {})[sensor_id])
        states = np.full((len(sm.truth_ids), 4), np.nan)
        for i, tid in enumerate(tr.target_ids):
            states[index[tid]] = tr.states[i]
        return _wire(side.survey(cmd.episode, cmd.scan, win, states), cmd, clock)

    return serve(
        sensor_id,
        bus,
        run_id,
        clock,
        stop,
        sc.network,
        truth_ok=truth_ok,
        respond=respond,
        scans=sm.scans,
        keep_truth=sm.scans <= msg.TRUTH_UPFRONT_MAX_SCANS,
        config=config_id(sc),
        command_ok=command_ok,
    )


def run_targets(
    sc: Scenario,
    sensor_id: str,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
) -> SensorStats:
    """A sensor of a many-target scenario (module docstring); serves commands until ``stop``
    is set."""
    from covnet.covariance_control import targets  # start-up: configs with targets only

    tm = targets.build(sc)
    j = tm.sensor_ids.index(sensor_id)
    model = tm.sensors[j]
    tids = tm.target_ids

    def truth_ok(tr: msg.Truth) -> bool:
        return tr.target_ids == tids and tr.states.shape == (len(tids), 4)

    def command_ok(cmd: msg.Command) -> bool:
        task = (cmd.targets or {}).get(sensor_id)
        if task is None or len(task) != 1 or task[0] not in tids:
            return False
        v = (cmd.windows or {}).get(sensor_id)
        if (v is None) != (model.clutter_rate == 0.0):
            return False
        try:
            targets.window_from_vec(tm, j, v)
        except ValueError:
            return False
        return True

    # what it sends: the kind's sensor side (the one covnet run hands over in process)
    side = SensorSide.of_process(sc, tm, j)

    def respond(cmd: msg.Command, tr: msg.Truth) -> msg.Measurement | msg.LocalTrack:
        t = tids.index((cmd.targets or {})[sensor_id][0])
        win = targets.window_from_vec(tm, j, (cmd.windows or {}).get(sensor_id))
        return _wire(side.dwell(cmd.episode, cmd.scan, t, win, tr.states[t]), cmd, clock)

    return serve(
        sensor_id,
        bus,
        run_id,
        clock,
        stop,
        sc.network,
        truth_ok=truth_ok,
        respond=respond,
        # slow links: every command (a stale one is ignored), a missed one is a scan off
        missed_command="off" if not sc.network.latency.is_ideal(sc.sensor_ids) else None,
        scans=tm.scans,
        keep_truth=tm.scans <= msg.TRUTH_UPFRONT_MAX_SCANS,
        config=config_id(sc),
        command_ok=command_ok,
    )


def run(
    sc: Scenario,
    sensor_id: str,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
) -> SensorStats:
    """A covariance-control position sensor; serves commands until ``stop`` is set.

    Under a track rule (:attr:`~covnet.covariance_control.fusion_rules.FusionRule.tracks`:
    ``info``, ``ci``) it runs its own local Kalman filter and publishes a
    :class:`~covnet.wire.messages.LocalTrack` instead of the measurement: the filter predicts every
    scan (lazily, scan by scan up to the commanded one: the same arithmetic as predicting at
    every scan) and updates at the scans it is enabled; a new episode restarts it from the
    initial estimate.  Many targets: :func:`run_targets`."""
    if sc.surveillance is not None:
        return run_surveillance(sc, sensor_id, bus, run_id, clock, stop)
    if sc.multitarget:
        return run_targets(sc, sensor_id, bus, run_id, clock, stop)
    model = build_model(sc)
    j = model.index(sensor_id)
    # what it sends: the kind's sensor side (the one covnet run hands over in process), its
    # noise drawn ahead
    table = NoiseTable(model, j, NoiseTable.reserve(model.scans))
    side = SensorSide.of_process(sc, model, j, table)

    def truth_ok(tr: msg.Truth) -> bool:
        return tr.states.shape[0] >= 1 and tr.states.shape[1] == 4

    def respond(cmd: msg.Command, tr: msg.Truth) -> msg.Measurement | msg.LocalTrack:
        m = side.respond(cmd.episode, cmd.scan, None, truth=tr.states[0])
        assert m is not None  # one target: every command it acts on is a measurement
        return _wire(m, cmd, clock)

    slow = not sc.network.latency.is_ideal(sc.sensor_ids)
    return serve(
        sensor_id,
        bus,
        run_id,
        clock,
        stop,
        sc.network,
        truth_ok=truth_ok,
        respond=respond,
        missed_command=sc.network.latency.missed_command if slow else None,
        scans=model.scans,
        keep_truth=model.scans <= msg.TRUTH_UPFRONT_MAX_SCANS,
        config=config_id(sc),
        fast=fast_respond(side, clock),
    )


def fast_respond(side: SensorSide, clock: Clock) -> FastRespond | None:
    """The payload of a one-target sensor's measurement for a command and truth, numbered
    ``seq``, from the sensor's :class:`~covnet.wire.batch_encode.MeasurementTemplate`: what
    ``msg.encode(_wire(side.respond(...), command, clock).evolve(seq=seq))`` gives, bit for bit
    (``side.respond``'s ``z``, its ``noisy(scan, x)``; the template's bytes are the codec's),
    without building the message twice and packing it field by field; ``None`` under a track
    rule (a local track is sent: the codec's path), or when the template takes no such sensor.
    The returned function gives ``None`` for a value the template does not take (the message
    is then built, and refused, as before)."""
    eng = side.engine
    if eng.tracks or eng.many or eng.surveil:
        return None
    template = MeasurementTemplate.of(side.sensor_id, eng.model.R[side.j])
    if template is None:
        return None
    encode, noisy, now_ns = template.encode_row, side.noisy, clock.now_ns

    def fast(cmd: msg.Command, tr: msg.Truth, seq: int) -> bytes | None:
        # side.respond's z (no track rule: its episode start keeps nothing), without its
        # Measured; a NoiseTable's scan from the table, or drawn where the table ends
        return encode(cmd.scan, cmd.t, noisy(cmd.scan, tr.states[0]), now_ns(), cmd.episode, seq)

    return fast


def _wire(
    m: Measured | Tracked, cmd: msg.Command, clock: Clock
) -> msg.Measurement | msg.LocalTrack:
    """The wire message of what the sensor side computed for ``cmd``'s scan (its time and the
    moment it is sent added)."""
    if isinstance(m, Tracked):
        return msg.LocalTrack(
            sensor_id=m.sensor_id,
            scan=m.scan,
            t=cmd.t,
            x=m.x,
            P=m.P,
            x_prior=m.x_prior,
            P_prior=m.P_prior,
            t_sent_ns=clock.now_ns(),
            episode=m.episode,
            target_id=m.target_id,
        )
    return msg.Measurement(
        sensor_id=m.sensor_id,
        scan=m.scan,
        t=cmd.t,
        z=m.z,
        R=m.R,
        t_sent_ns=clock.now_ns(),
        episode=m.episode,
    )


class NoiseTable:
    """``noisy(k, x)`` is :func:`covnet.covariance_control.model.measure` ``(model, j, k, x)`` bit
    for bit, with the noise of the first scans drawn ahead, at start-up: the noise stream
    ``(seed, j, k)`` does not depend on the truth, and building a generator per scan is most of
    a measurement's cost on the scan's critical path.  The measurement is ``H x + v``: ``v`` is
    taken as ``measure(model, j, k, 0)`` (``0 + v`` is ``v`` exactly unless ``v`` holds a zero,
    then that scan is drawn as before), and a start-up check falls back to :func:`measure` for
    every scan if the model is not of that form.

    How far ahead: at most :attr:`MAX_SCANS` scans a sensor and :attr:`PROCESS_DRAWS` draws in
    a process (its hosted sensors together, first come first served); later scans are drawn
    when they are measured.  A table of every scan of a long run made a large network's start
    too slow for the manager's ``ready_timeout_s``: 256 sensors in four processes, each drawing
    20 000 scans at start-up, were not alive after the 30 s it waits (two cores)."""

    MAX_SCANS = 20_000
    PROCESS_DRAWS = 400_000

    _reserved = 0  # draws reserved in this process (:meth:`reserve`)
    _lock = threading.Lock()

    @classmethod
    def reserve(cls, scans: int) -> int:
        """How many of a sensor's first ``scans`` scans its table may draw at start-up in this
        process: at most :attr:`MAX_SCANS`, and what is left of :attr:`PROCESS_DRAWS` after
        the hosted sensors that asked before (first come, first served)."""
        with cls._lock:
            ahead = max(0, min(scans, cls.MAX_SCANS, cls.PROCESS_DRAWS - cls._reserved))
            cls._reserved += ahead
        return ahead

    def __init__(self, model: Model, j: int, ahead: int | None = None) -> None:
        """The table of sensor ``j``'s first ``ahead`` scans (default: every scan of the run,
        at most :attr:`MAX_SCANS`; a sensor process asks :meth:`reserve`)."""
        self.model, self.j, self.H = model, j, model.H
        if ahead is None:
            ahead = min(model.scans, self.MAX_SCANS)
        zero = np.zeros(model.H.shape[1])
        table: dict[int, np.ndarray] = {}
        for k in range(1, ahead + 1):
            v = measure(model, j, k, zero)
            if v.all():  # no zero entry: H x + v is then exactly what measure draws
                table[k] = v
        x = np.arange(1.0, model.H.shape[1] + 1.0) * 1000.0 + 0.123
        if 1 in table and not np.array_equal(model.H @ x + table[1], measure(model, j, 1, x)):
            table = {}  # not H x + v: draw every scan
        self.table = table

    def __call__(self, scan: int, x: np.ndarray) -> np.ndarray:
        z = self.tabled(scan, x)
        return measure(self.model, self.j, scan, x) if z is None else z

    def tabled(self, scan: int, x: np.ndarray) -> np.ndarray | None:
        """``H x + v`` with the scan's noise ``v`` from the table; None for a scan it lacks."""
        v = self.table.get(scan)
        return None if v is None else self.H @ x + v
