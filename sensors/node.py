"""A sensor's loop: obey the manager's commands, measure the truth, publish.

A sensor subscribes to the commands that enable it (the command's key names the enabled set,
:func:`covnet.messages.command_key`; zenoh delivers a command to the sensors it enables only, so
a disabled sensor is not woken).  Per command for scan ``k`` that lists it in ``enabled``, it
waits for the world's ``Truth(k)``, draws its measurement ``z = H x + v`` from its own noise
stream ``(seed, j, k)`` (:func:`covnet.model.measure`, the same draw ``covnet run`` makes) and
publishes ``Measurement(k)``; at a scan that does not enable it, it publishes nothing.  On slow
links it hears every command (to notice one it missed: ``missed_command``).  A command whose
truth never comes (a sensor restarted after the world sent it) is dropped as soon as a newer
command arrives, so a sensor never stalls on a scan that has passed.  It sends a heartbeat
every ``network.heartbeat_s`` (a hung loop stops sending them) and declares its liveliness
token once its subscriptions exist.  Malformed messages are counted by reason and dropped.
The measurement noise of every scan is drawn at start-up (:class:`NoiseTable`): that takes
work off the scan's critical path and changes no result.
It ends on ``stop`` or when the manager it has seen leaves (its liveliness token goes: the run
is over, or the manager died).
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from covnet import messages as msg
from covnet.bus import Bus, Sample
from covnet.clock import Clock
from covnet.config import NetworkSpec, Scenario
from covnet.core.gaussian import Gaussian
from covnet.decentral import local_track
from covnet.model import Model, build_model, initial_estimate, measure, predict_step
from covnet.node_kit import Heartbeat, ManagerWatch


@dataclass
class SensorStats:
    commands: int = 0
    enabled_scans: int = 0
    measurements_sent: int = 0
    missed_truth: int = 0  # commanded scans whose truth never came (e.g. just after a restart)
    missed_commands: int = 0  # scans whose command never came (slow links)
    rejected: Counter[str] = field(default_factory=Counter)


TruthCheck = Callable[[msg.Truth], bool]
Respond = Callable[[msg.Command, msg.Truth], msg.Measurement]


def serve(
    sensor_id: str,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    net: NetworkSpec,
    *,
    truth_ok: TruthCheck,
    respond: Respond,
    missed_command: str | None = None,
    keep_truth: bool = False,
) -> SensorStats:
    """The protocol every kind of sensor shares (see the module docstring).

    ``truth_ok(truth)`` says whether a decoded ``Truth`` is usable by this sensor (else it is
    counted as ``bad_shape``); ``respond(command, truth)`` makes the measurement message for
    an enabled command once its scan's truth is in hand.  Returns the sensor's counters.

    ``missed_command`` (slow links, ``network.latency.missed_command``): a command older than
    the newest one received is stale and ignored; scans whose command never came (a gap before
    the command just received) are filled by the policy, ``keep_last`` (the newest command's
    on/off for this sensor), ``off`` or ``on``, and measured at once (so late: the manager
    re-filters or drops them).  ``keep_truth``: keep every scan's truth for the whole run (the
    world sends it once, :data:`~covnet.messages.TRUTH_UPFRONT_MAX_SCANS`), else drop what is
    older than the scan being measured (the world sends it again for a new episode)."""
    stats = SensorStats()
    # on slow links every command (a gap in the scans says one was missed), else its own
    mine = None if missed_command is not None else sensor_id
    cmd_sub = bus.subscribe(msg.command_keyexpr(run_id, mine))
    truth_sub = bus.subscribe(msg.truth_key(run_id))
    manager = ManagerWatch(bus, run_id)
    token = bus.declare_token(msg.alive_key(run_id, "sensor", sensor_id))
    meas_key = msg.measurement_key(run_id, sensor_id)
    heartbeat = Heartbeat(bus, clock, run_id, "sensor", sensor_id, net.heartbeat_s)
    wait_s = net.heartbeat_s / 2
    truths: dict[int, msg.Truth] = {}
    pending: deque[msg.Command] = deque()  # enabled commands not yet answered, oldest first
    last_scan = 0
    newest = (-1, 0)  # (episode, scan) of the newest command received
    last_on = False

    def accept(s: Sample | None) -> bool:
        """Decode one command; queue it if this sensor is enabled. False when ``s`` is None."""
        nonlocal last_scan
        if s is None:
            return False
        try:
            cmd = msg.decode_command(s.key, s.payload)
        except msg.WireError as exc:
            stats.rejected[exc.reason] += 1
            return True
        nonlocal newest, last_on
        stats.commands += 1
        if missed_command is not None:
            if (cmd.episode, cmd.scan) <= newest:
                stats.rejected["stale_command"] += 1
                return True
            first = newest[1] + 1 if cmd.episode == newest[0] else 1
            for m in range(first, cmd.scan):  # commands that never came: the fallback
                stats.missed_commands += 1
                if {"keep_last": last_on, "off": False, "on": True}[missed_command]:
                    t_m = cmd.t * m / cmd.scan  # t = scan * period
                    pending.append(
                        msg.Command(m, t_m, (sensor_id,), cmd.t_sent_ns, episode=cmd.episode)
                    )
            newest, last_on = (cmd.episode, cmd.scan), sensor_id in cmd.enabled
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
        if not truth_ok(tr):
            stats.rejected["bad_shape"] += 1
            return True
        truths[tr.scan] = tr
        return True

    try:
        while not stop.is_set():
            heartbeat.tick(last_scan, stats.rejected)
            if manager.left:
                break
            if pending:  # waiting for a commanded scan's truth
                take_truth(wait_s)
            else:
                accept(cmd_sub.recv(timeout=wait_s))
            while accept(cmd_sub.try_recv()):
                pass
            while take_truth(None):
                pass
            while pending:
                cmd = pending[0]
                if cmd.scan in truths:
                    bus.publish(meas_key, msg.encode(respond(cmd, truths[cmd.scan])))
                    stats.measurements_sent += 1
                    if not keep_truth:
                        for old in [k for k in truths if k < cmd.scan - 1]:
                            del truths[old]
                elif len(pending) > 1:  # a newer command came first: this truth is gone
                    stats.missed_truth += 1
                else:
                    break
                pending.popleft()
    finally:
        token.undeclare()
        manager.close()
    return stats


def run(
    sc: Scenario,
    sensor_id: str,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
) -> SensorStats:
    """A covariance-control position sensor; serves commands until ``stop`` is set.

    In the decentralized centre modes (``fusion.mode: info | ci``) it runs its own local Kalman
    filter and publishes a :class:`~covnet.messages.LocalTrack` instead of the measurement: the
    filter predicts every scan (lazily, scan by scan up to the commanded one: the same
    arithmetic as predicting at every scan) and updates at the scans it is enabled; a new
    episode restarts it from the initial estimate."""
    model = build_model(sc)
    j = model.index(sensor_id)
    R = model.R[j]
    local = LocalFilter(model, sc.filter.initial_estimate)
    noisy = NoiseTable(model, j)

    def truth_ok(tr: msg.Truth) -> bool:
        return tr.states.shape[0] >= 1 and tr.states.shape[1] == 4

    def respond_track(cmd: msg.Command, tr: msg.Truth) -> msg.LocalTrack:
        prior = local.predict_to(cmd.episode, cmd.scan)
        track = local_track(model, j, prior, noisy(cmd.scan, tr.states[0]))
        local.set(track.post)
        return msg.LocalTrack(
            sensor_id=sensor_id,
            scan=cmd.scan,
            t=cmd.t,
            x=track.post.x,
            P=track.post.P,
            x_prior=prior.x,
            P_prior=prior.P,
            t_sent_ns=clock.now_ns(),
            episode=cmd.episode,
        )

    def respond(cmd: msg.Command, tr: msg.Truth) -> msg.Measurement:
        z = noisy(cmd.scan, tr.states[0])
        return msg.Measurement(
            sensor_id=sensor_id,
            scan=cmd.scan,
            t=cmd.t,
            z=z[None, :],
            R=R,
            t_sent_ns=clock.now_ns(),
            episode=cmd.episode,
        )

    decentral = sc.fusion.mode in ("info", "ci")
    slow = not sc.network.latency.is_ideal(sc.sensor_ids)
    return serve(
        sensor_id,
        bus,
        run_id,
        clock,
        stop,
        sc.network,
        truth_ok=truth_ok,
        respond=respond_track if decentral else respond,  # type: ignore[arg-type]
        missed_command=sc.network.latency.missed_command if slow else None,
        keep_truth=model.scans <= msg.TRUTH_UPFRONT_MAX_SCANS,
    )


class NoiseTable:
    """``noisy(k, x)`` is :func:`covnet.model.measure` ``(model, j, k, x)`` bit for bit, with
    the noise of every scan drawn ahead, at start-up (up to :attr:`MAX_SCANS`): the noise
    stream ``(seed, j, k)`` does not depend on the truth, and building a generator per scan
    is most of a measurement's cost on the scan's critical path.  The measurement is
    ``H x + v``: ``v`` is taken as ``measure(model, j, k, 0)`` (``0 + v`` is ``v`` exactly
    unless ``v`` holds a zero, then that scan is drawn as before), and a start-up check falls
    back to :func:`measure` for every scan if the model is not of that form."""

    MAX_SCANS = 20_000

    def __init__(self, model: Model, j: int) -> None:
        self.model, self.j, self.H = model, j, model.H
        zero = np.zeros(model.H.shape[1])
        table: dict[int, np.ndarray] = {}
        for k in range(1, min(model.scans, self.MAX_SCANS) + 1):
            v = measure(model, j, k, zero)
            if np.all(v != 0.0):
                table[k] = v
        x = np.arange(1.0, model.H.shape[1] + 1.0) * 1000.0 + 0.123
        if 1 in table and not np.array_equal(model.H @ x + table[1], measure(model, j, 1, x)):
            table = {}  # not H x + v: draw every scan
        self.table = table

    def __call__(self, scan: int, x: np.ndarray) -> np.ndarray:
        v = self.table.get(scan)
        if v is None:
            return measure(self.model, self.j, scan, x)
        return self.H @ x + v


class LocalFilter:
    """A sensor's own Kalman filter over the scans of one episode (decentralized modes):
    ``predict_to(episode, k)`` returns its prediction for scan ``k`` (a new episode restarts
    from the initial estimate at scan 0); ``set(posterior)`` stores the update of that scan."""

    def __init__(self, model: Model, initial: str) -> None:
        self.model, self.initial = model, initial
        self.episode, self.scan = -1, 0
        self.estimate: Gaussian = initial_estimate(model, initial)

    def predict_to(self, episode: int, scan: int) -> Gaussian:
        if episode != self.episode:
            self.episode, self.scan = episode, 0
            self.estimate = initial_estimate(self.model, self.initial)
        g = self.estimate
        while self.scan < scan:
            g = predict_step(self.model, g)
            self.scan += 1
        self.estimate = g
        return g

    def set(self, posterior: Gaussian) -> None:
        self.estimate = posterior
