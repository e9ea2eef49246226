"""The protocol every kind of sensor process shares: commands in, truth in, measurements out.

A sensor subscribes to the commands that enable it (the command's key names the enabled set,
:func:`covnet.wire.messages.command_key`; zenoh delivers a command to the sensors it enables only,
so
a disabled sensor is not woken).  Per command for scan ``k`` that lists it in ``enabled``, it
waits for the world's ``Truth(k)``, makes its measurement message from that truth (the kind's
``respond``: :mod:`sensors.covariance`, :mod:`sensors.mobile`, :mod:`sensors.passive`) and
publishes it; at a scan that does not enable it, it publishes nothing.  On slow links it hears
every command (to notice one it missed: ``missed_command``).  A command whose truth never comes
(a sensor restarted after the world sent it) is dropped as soon as a newer command arrives, so a
sensor never stalls on a scan that has passed.  It sends a heartbeat every
``network.heartbeat_s`` (a hung loop stops sending them) and declares its liveliness token once
its subscriptions exist.  Malformed messages are counted by reason and dropped.  It ends on
``stop`` or when the manager it has seen leaves (its liveliness token goes: the run is over, or
the manager died).

:func:`process_main` is what every sensor role module's ``main`` does around :func:`serve`.
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from covnet.clock import Clock, WallClock
from covnet.config import NetworkSpec
from covnet.core.delay import measures_on_missed
from covnet.processes.node_kit import Heartbeat, ManagerWatch, manager_grace_s
from covnet.processes.process import EXIT_OK, open_client
from covnet.wire import messages as msg
from covnet.wire.bus import Bus, Sample
from covnet.wire.profiling import Stages, profiled
from sensors.host import say


@dataclass
class SensorStats:
    commands: int = 0
    enabled_scans: int = 0
    measurements_sent: int = 0
    missed_truth: int = 0  # commanded scans whose truth never came (e.g. just after a restart)
    missed_commands: int = 0  # scans whose command never came (slow links)
    rejected: Counter[str] = field(default_factory=Counter)


TruthCheck = Callable[[msg.Truth], bool]
Respond = Callable[[msg.Command, msg.Truth], msg.Measurement | msg.LocalTrack]


_SHARED_MAX = 1024
_shared: dict[tuple[str, bytes], msg.Command | msg.Truth | msg.WireError] = {}


def _shared_decode(key: str, payload: bytes, decode: Any) -> Any:
    """``decode()`` of the message ``payload`` received on ``key``, once for all the sensors of
    a process (:mod:`sensors.host`): each hosted sensor receives the same commands and truths
    (the same keys and bytes), and decoding a command, every id of its enabled set checked,
    is most of a sensor's work for a scan when hundreds are enabled.  Outcomes are kept by key
    and bytes (at most :data:`_SHARED_MAX`, then forgotten all at once): a message is
    immutable, so the sensors share it; a refusal is raised again, as a new error of the same
    reason."""
    tag = (key, payload)
    out = _shared.get(tag)
    if out is None:
        try:
            out = decode()
        except msg.WireError as exc:
            out = exc
        if len(_shared) >= _SHARED_MAX:
            _shared.clear()
        _shared[tag] = out
    if isinstance(out, msg.WireError):
        raise msg.WireError(out.reason, out.detail)
    return out


def decode_command(key: str, payload: bytes) -> msg.Command:
    """:func:`covnet.wire.messages.decode_command`, shared by the sensors of a process
    (:func:`_shared_decode`)."""
    out: msg.Command = _shared_decode(key, payload, lambda: msg.decode_command(key, payload))
    return out


def decode_truth(key: str, payload: bytes) -> msg.Truth:
    """``decode_as(payload, Truth)``, shared by the sensors of a process
    (:func:`_shared_decode`)."""
    out: msg.Truth = _shared_decode(key, payload, lambda: msg.decode_as(payload, msg.Truth))
    return out


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
    command_ok: Callable[[msg.Command], bool] | None = None,
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
    world sends it once, :data:`~covnet.wire.messages.TRUTH_UPFRONT_MAX_SCANS`), else drop what is
    older than the scan being measured (the world sends it again for a new episode).
    ``command_ok(command)``: the kind's test of an enabling command's fields (its task for this
    sensor); one it fails is counted ``bad_value`` and not answered."""
    with profiled(f"sensor-{sensor_id}"):
        return _serve(
            sensor_id, bus, run_id, clock, stop, net, truth_ok=truth_ok, respond=respond,
            missed_command=missed_command, keep_truth=keep_truth, command_ok=command_ok,
        )  # fmt: skip


def _serve(
    sensor_id: str,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    net: NetworkSpec,
    *,
    truth_ok: TruthCheck,
    respond: Respond,
    missed_command: str | None,
    keep_truth: bool,
    command_ok: Callable[[msg.Command], bool] | None,
) -> SensorStats:
    stats = SensorStats()
    # on slow links every command (a gap in the scans says one was missed), else its own
    mine = None if missed_command is not None else sensor_id
    cmd_sub = bus.subscribe(msg.command_keyexpr(run_id, mine))
    truth_sub = bus.subscribe(msg.truth_key(run_id))
    manager = ManagerWatch(bus, run_id, manager_grace_s(net))
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
            cmd = decode_command(s.key, s.payload)
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
                if measures_on_missed(missed_command, last_on):
                    t_m = cmd.t * m / cmd.scan  # t = scan * period
                    pending.append(
                        msg.Command(m, t_m, (sensor_id,), cmd.t_sent_ns, episode=cmd.episode)
                    )
            newest, last_on = (cmd.episode, cmd.scan), sensor_id in cmd.enabled
        last_scan = cmd.scan
        if sensor_id in cmd.enabled:
            if command_ok is not None and not command_ok(cmd):
                stats.rejected["bad_value"] += 1
                return True
            stats.enabled_scans += 1
            pending.append(cmd)
        return True

    def take_truth(timeout: float | None) -> bool:
        s = truth_sub.recv(timeout) if timeout is not None else truth_sub.try_recv()
        if s is None:
            return False
        try:
            tr = decode_truth(s.key, s.payload)
        except msg.WireError as exc:
            stats.rejected[exc.reason] += 1
            return True
        if not truth_ok(tr):
            stats.rejected["bad_shape"] += 1
            return True
        truths[tr.scan] = tr
        return True

    stages = Stages()  # the loop's time by stage (covnet bench up --profile; off by default)
    lap = stages.lap
    try:
        while not stop.is_set():
            heartbeat.tick(last_scan, stats.rejected, sent=stats.measurements_sent)
            if manager.left:
                break
            lap("heartbeat")
            if pending:  # waiting for a commanded scan's truth
                take_truth(wait_s)
                lap("wait: truth")
            else:
                s = cmd_sub.recv(timeout=wait_s)
                lap("wait: command")
                accept(s)
                lap("command")
            while accept(cmd_sub.try_recv()):
                pass
            while take_truth(None):
                pass
            lap("drain")
            while pending:
                cmd = pending[0]
                if cmd.scan in truths:
                    out = respond(cmd, truths[cmd.scan]).evolve(seq=stats.measurements_sent + 1)
                    lap("respond")
                    payload = msg.encode(out)
                    lap("encode")
                    bus.publish(meas_key, payload)
                    lap("publish")
                    stats.measurements_sent += 1
                    if not keep_truth:
                        for old in [k for k in truths if k < cmd.scan - 1]:
                            del truths[old]
                elif len(pending) > 1:  # a newer command came first: this truth is gone
                    stats.missed_truth += 1
                else:
                    break
                pending.popleft()
    finally:  # the last count, for the manager (its last messages may be lost) and the record
        heartbeat.tick(last_scan, stats.rejected, sent=stats.measurements_sent, now=True)
        token.undeclare()
        manager.close()
        stages.dump(f"sensor-{sensor_id}", sent=stats.measurements_sent)
    return stats


def process_main(
    args: Any,
    cfg: Any,
    stop: threading.Event,
    run: Callable[[Any, str, Bus, str, Clock, threading.Event], SensorStats],
    wrap: Callable[[Bus], Any] | None = None,
) -> int:
    """A sensor process around its loop: open the client session, run ``run(cfg, id, bus,
    run_id, clock, stop)`` (over ``wrap(bus)`` when given: a bus that emulates the links, say;
    closed afterwards), print the counters, exit 0."""
    with open_client(args, cfg.network, "sensor", args.id, stop) as bus:
        wrapped = wrap(bus) if wrap is not None else None
        try:
            stats = run(cfg, args.id, wrapped or bus, args.run, WallClock(args.speed), stop)
        finally:
            if wrapped is not None:
                wrapped.close()
    say(
        args,
        f"stopped: {stats.commands} commands received, {stats.enabled_scans} scans enabled, "
        f"{stats.measurements_sent} measurements sent, rejected {dict(stats.rejected)}",
    )
    return EXIT_OK
