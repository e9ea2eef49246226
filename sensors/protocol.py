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
``network.heartbeat_s`` (a hung loop stops sending them), except that a measurement stands for
one (the manager takes any of its messages as a sign of life: a sensor measuring every scan
sends a heartbeat only when it has new rejections to report, and as it leaves), and declares its
liveliness token once its subscriptions exist.  Malformed messages are counted by reason and
dropped.  It ends on ``stop`` or when the manager it has seen leaves (its liveliness token
goes: the run is over, or the manager died).

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
from covnet.processes.node_kit import (
    Heartbeat,
    ManagerWatch,
    manager_appear_s,
    manager_grace_s,
    not_ended_well,
)
from covnet.processes.process import EXIT_OK, EXIT_RUN_FAILED, open_client
from covnet.wire import messages as msg
from covnet.wire.bus import Bus, Sample, Subscription, Token
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
    #: the sensor left because the run did not end well: its manager ended it with an error or
    #: went away without ending it (:attr:`~covnet.processes.node_kit.ManagerWatch.crashed`)
    manager_lost: bool = False


TruthCheck = Callable[[msg.Truth], bool]
Respond = Callable[[msg.Command, msg.Truth], msg.Measurement | msg.LocalTrack]
#: ``fast(command, truth, seq)``: the payload ``encode(respond(command, truth).evolve(seq=seq))``
#: would be, bit for bit, made without building the message; ``None``: take that path instead
FastRespond = Callable[[msg.Command, msg.Truth, int], bytes | None]


TRUTHS_NEAR = 32
"""A sensor that keeps no run's truth (a run above ``TRUTH_UPFRONT_MAX_SCANS``: the world sends
windows of 17 scans ahead) and has no command waiting keeps the truths within this many scans
of the newest: two windows."""
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
    scans: int,
    missed_command: str | None = None,
    keep_truth: bool = False,
    command_ok: Callable[[msg.Command], bool] | None = None,
    fast: FastRespond | None = None,
    config: str | None = None,
) -> SensorStats:
    """The protocol every kind of sensor shares (see the module docstring).

    ``truth_ok(truth)`` says whether a decoded ``Truth`` is usable by this sensor (else it is
    counted as ``bad_shape``); ``respond(command, truth)`` makes the measurement message for
    an enabled command once its scan's truth is in hand.  Returns the sensor's counters.
    ``scans``: the run's number of scans; a truth of a scan outside ``1..scans`` is counted
    ``bad_scan`` and not kept (a sensor keeps the truths of scans to come: forged ones of
    scans that never come filled its memory).

    ``missed_command`` (slow links, ``network.latency.missed_command``): a command older than
    the newest one received is stale and ignored; scans whose command never came (a gap before
    the command just received) are filled by the policy, ``keep_last`` (the newest command's
    on/off for this sensor), ``off`` or ``on``, and measured at once (so late: the manager
    re-filters or drops them).  ``keep_truth``: keep every scan's truth for the whole run (the
    world sends it once, :data:`~covnet.wire.messages.TRUTH_UPFRONT_MAX_SCANS`), else drop what is
    older than the scan being measured (the world sends it again for a new episode).
    ``command_ok(command)``: the kind's test of an enabling command's fields (its task for this
    sensor); one it fails is counted ``bad_value`` and not answered.  ``fast`` (optional):
    ``fast(command, truth, seq)`` is the payload of ``respond(command, truth)`` numbered
    ``seq``, the same bytes made without building the message (``sensors.covariance``: a
    measurement from its :class:`~covnet.wire.batch_encode.MeasurementTemplate`), or ``None``
    for a case it does not take (then ``respond`` and the codec).  ``config``: the sensor's
    :func:`~covnet.processes.node_kit.config_id`, in its heartbeats."""
    with profiled(f"sensor-{sensor_id}"):
        return _serve(
            sensor_id, bus, run_id, clock, stop, net, truth_ok=truth_ok, respond=respond,
            scans=scans, missed_command=missed_command, keep_truth=keep_truth,
            command_ok=command_ok, fast=fast, config=config,
        )  # fmt: skip


class _Sensor:
    """One sensor's side of the protocol (module docstring): its counters, the commands it
    must answer and the truths it holds, fed by a loop that owns the subscriptions (its own,
    :func:`_serve`; or its host's, shared by every sensor of the process, :class:`HostLoop`)."""

    def __init__(
        self,
        sensor_id: str,
        bus: Bus,
        run_id: str,
        clock: Clock,
        net: NetworkSpec,
        *,
        truth_ok: TruthCheck,
        respond: Respond,
        scans: int,
        missed_command: str | None,
        keep_truth: bool,
        command_ok: Callable[[msg.Command], bool] | None,
        fast: FastRespond | None = None,
        config: str | None = None,
    ) -> None:
        self.id, self.bus, self.run_id, self.clock = sensor_id, bus, run_id, clock
        self.scans = scans
        self.truth_ok, self.respond, self.fast = truth_ok, respond, fast
        self.missed_command, self.keep_truth, self.command_ok = (
            missed_command, keep_truth, command_ok,
        )  # fmt: skip
        self.stats = SensorStats()
        #: the sub-chunk a command key carries when it enables this sensor (``$*~<id>~$*``)
        self.tag = f"~{sensor_id}~"
        self.meas_key = msg.measurement_key(run_id, sensor_id)
        self.heartbeat = Heartbeat(
            bus, clock, run_id, "sensor", sensor_id, net.heartbeat_s, config
        )
        self.truths: dict[int, msg.Truth] = {}
        self.pending: deque[msg.Command] = deque()  # enabled commands not yet answered
        self.last_scan = 0
        self.newest = (-1, 0)  # (episode, scan) of the newest command received
        self.last_on = False
        self.token: Token | None = None  # its liveliness token, declared by its loop
        self.told_rejected = 0  # rejections its last heartbeat reported

    def hears(self, key: str, chunk: str | None = None) -> bool:
        """Whether this sensor's own subscription would receive a command on ``key``: every
        command on slow links, else those whose key names it (zenoh's ``$*~<id>~$*``).
        ``chunk``: the key's last chunk, when the caller cut it once for several sensors."""
        if self.missed_command is not None:
            return True
        return self.tag in (chunk if chunk is not None else key.rpartition("/")[2])

    def tick(self, now: bool = False) -> None:
        st = self.stats
        if self.heartbeat.tick(self.last_scan, st.rejected, sent=st.measurements_sent, now=now):
            self.told_rejected = st.rejected.total()

    def accept(
        self, cmd: msg.Command | msg.WireError, enabled: frozenset[str] | None = None
    ) -> None:
        """One command received (or why it was refused); queued if this sensor is enabled.
        ``enabled``: ``frozenset(cmd.enabled)``, when the caller made it once for the
        sensors of a host (``id in cmd.enabled`` scans the tuple: N compares for N ids)."""
        stats = self.stats
        if isinstance(cmd, msg.WireError):
            stats.rejected[cmd.reason] += 1
            return
        if not 1 <= cmd.scan <= self.scans:
            # a scan the run does not have (on slow links one of 10**9 made every sensor
            # fill in the scans up to it, one command each: hours, and the memory)
            stats.rejected["bad_scan"] += 1
            return
        stats.commands += 1
        sensor_id = self.id
        on = sensor_id in (enabled if enabled is not None else cmd.enabled)
        if self.missed_command is not None:
            if (cmd.episode, cmd.scan) <= self.newest:
                stats.rejected["stale_command"] += 1
                return
            newest = self.newest
            first = newest[1] + 1 if cmd.episode == newest[0] else 1
            for m in range(first, cmd.scan):  # commands that never came: the fallback
                stats.missed_commands += 1
                if measures_on_missed(self.missed_command, self.last_on):
                    t_m = cmd.t * m / cmd.scan  # t = scan * period
                    self.pending.append(
                        msg.Command(m, t_m, (sensor_id,), cmd.t_sent_ns, episode=cmd.episode)
                    )
            self.newest, self.last_on = (cmd.episode, cmd.scan), on
        self.last_scan = cmd.scan
        if on:
            if self.command_ok is not None and not self.command_ok(cmd):
                stats.rejected["bad_value"] += 1
                return
            stats.enabled_scans += 1
            self.pending.append(cmd)

    def take_truth(self, tr: msg.Truth | msg.WireError) -> None:
        """One truth received (or why it was refused)."""
        if isinstance(tr, msg.WireError):
            self.stats.rejected[tr.reason] += 1
        elif not 1 <= tr.scan <= self.scans:
            self.stats.rejected["bad_scan"] += 1
        elif not self.truth_ok(tr):
            self.stats.rejected["bad_shape"] += 1
        else:
            truths = self.truths
            truths[tr.scan] = tr
            if not self.keep_truth and not self.pending and len(truths) > 2 * TRUTHS_NEAR + 1:
                # nothing waits for a truth: keep those near the newest (a sensor no scan
                # enables answered nothing, so its truths were never dropped: 0.5 kB a scan)
                for old in [k for k in truths if abs(k - tr.scan) > TRUTHS_NEAR]:
                    del truths[old]

    def answer(self, lap: Callable[[str], None]) -> None:
        """Publish the measurement of every pending command whose truth is in hand, oldest
        first; a command whose truth is gone (a newer one came first) is counted and dropped."""
        pending, truths, stats = self.pending, self.truths, self.stats
        while pending:
            cmd = pending[0]
            if cmd.scan in truths:
                seq = stats.measurements_sent + 1
                fast = self.fast
                payload = None if fast is None else fast(cmd, truths[cmd.scan], seq)
                if payload is None:
                    out = self.respond(cmd, truths[cmd.scan]).evolve(seq=seq)
                    lap("respond")
                    payload = msg.encode(out)
                    lap("encode")
                else:
                    lap("respond+encode (template)")
                self.bus.publish(self.meas_key, payload)
                stats.measurements_sent += 1
                if stats.rejected.total() == self.told_rejected:
                    self.heartbeat.touch()  # the measurement is its sign of life
                lap("publish")
                if not self.keep_truth:
                    for old in [k for k in truths if k < cmd.scan - 1]:
                        del truths[old]
            elif len(pending) > 1:  # a newer command came first: this truth is gone
                stats.missed_truth += 1
            else:
                break
            pending.popleft()


def _command(s: Sample) -> msg.Command | msg.WireError:
    try:
        return decode_command(s.key, s.payload)
    except msg.WireError as exc:
        return exc


def _truth(s: Sample) -> msg.Truth | msg.WireError:
    try:
        return decode_truth(s.key, s.payload)
    except msg.WireError as exc:
        return exc


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
    scans: int,
    missed_command: str | None,
    keep_truth: bool,
    command_ok: Callable[[msg.Command], bool] | None,
    fast: FastRespond | None,
    config: str | None,
) -> SensorStats:
    one = _Sensor(
        sensor_id, bus, run_id, clock, net, truth_ok=truth_ok, respond=respond, scans=scans,
        missed_command=missed_command, keep_truth=keep_truth, command_ok=command_ok, fast=fast,
        config=config,
    )  # fmt: skip
    host = _hosts.get(id(getattr(bus, "session", None)))
    if host is not None and host.takes(one):
        return host.serve(one, stop)
    # on slow links every command (a gap in the scans says one was missed), else its own
    mine = None if missed_command is not None else sensor_id
    cmd_sub = bus.subscribe(msg.command_keyexpr(run_id, mine))
    truth_sub = bus.subscribe(msg.truth_key(run_id))
    manager = ManagerWatch(bus, run_id, manager_grace_s(net), manager_appear_s(net))
    token = bus.declare_token(msg.alive_key(run_id, "sensor", sensor_id))
    wait_s = net.heartbeat_s / 2

    stages = Stages()  # the loop's time by stage (covnet bench up --profile; off by default)
    lap = stages.lap
    try:
        while not stop.is_set():
            one.tick()
            if manager.left:
                one.stats.manager_lost = manager.crashed
                break
            lap("heartbeat")
            if one.pending:  # waiting for a commanded scan's truth
                if (t := truth_sub.recv(wait_s)) is not None:
                    one.take_truth(_truth(t))
                lap("wait: truth")
            else:
                s = cmd_sub.recv(timeout=wait_s)
                lap("wait: command")
                if s is not None:
                    one.accept(_command(s))
                lap("command")
            while (s := cmd_sub.try_recv()) is not None:
                one.accept(_command(s))
            while (t := truth_sub.try_recv()) is not None:
                one.take_truth(_truth(t))
            lap("drain")
            one.answer(lap)
    finally:  # the last count, for the manager (its last messages may be lost) and the record
        one.tick(now=True)
        token.undeclare()
        manager.close()
        stages.dump(f"sensor-{sensor_id}", sent=one.stats.measurements_sent)
    return one.stats


class HostLoop:
    """The one loop of a process hosting several sensors on one session (:mod:`sensors.host`):
    one thread, one command and one truth subscription and one watch on the manager for all
    of them, instead of a thread, two subscriptions and a watch per sensor.

    Each hosted sensor's thread still runs its kind's ``main`` (its model, its noise, its
    ``respond``) up to :func:`serve`, which hands the sensor's protocol state (:class:`_Sensor`)
    to this loop and waits: the last one to arrive runs the loop for all, the others return
    their counters when it ends.  What each sensor receives, answers, counts and publishes
    (its own keys, publishers, liveliness token and heartbeat) is what its own loop would:
    the command subscription hears every command (``cmd/*``) and gives each sensor those its
    own key expression would match (:meth:`_Sensor.hears`); a command or truth is decoded
    once for all of them.  On the wire nothing changes: zenoh delivered a command once to the
    process's session before too, then once to each sensor's subscription in the process."""

    def __init__(self, bus: Bus, ids: list[str], net: NetworkSpec) -> None:
        self.bus, self.ids = bus, frozenset(ids)
        self.grace_s = manager_grace_s(net)
        self.appear_s = manager_appear_s(net)
        self.wait_s = net.heartbeat_s / 2
        self.expected = len(ids)
        self.sensors: list[_Sensor] = []
        self.lock = threading.Lock()
        self.started = False
        self.done = threading.Event()
        self.subs: tuple[Subscription, Subscription, ManagerWatch] | None = None

    def takes(self, one: _Sensor) -> bool:
        """Whether ``one`` joins this loop: a sensor of this host on a share of its session."""
        session = getattr(self.bus, "session", None)
        return one.id in self.ids and getattr(one.bus, "session", None) is session

    def serve(self, one: _Sensor, stop: threading.Event) -> SensorStats:
        """Hand ``one`` to the loop (class docstring); returns its counters when the loop
        ends (at once if the process stops before every hosted sensor arrived)."""
        with self.lock:
            run_id = one.run_id
            if self.subs is None:  # the subscriptions exist before any token
                self.subs = (
                    self.bus.subscribe(msg.command_keyexpr(run_id)),
                    self.bus.subscribe(msg.truth_key(run_id)),
                    ManagerWatch(self.bus, run_id, self.grace_s, self.appear_s),
                )
            one.token = token = one.bus.declare_token(msg.alive_key(run_id, "sensor", one.id))
            self.sensors.append(one)
        while True:
            with self.lock:
                runs = not self.started and len(self.sensors) >= self.expected
                self.started = self.started or runs
                if not self.started and stop.is_set():  # a hosted sensor never came
                    self.sensors.remove(one)
                    self.expected -= 1
                    break
            if runs:
                try:
                    self._run(stop)
                finally:
                    self.done.set()
                return one.stats
            # once the loop runs it ends by setting done (its finally): no polling meanwhile
            # (64 hosted threads woken 10 times a second each, for nothing)
            if self.done.wait(None if self.started else 0.1):
                return one.stats
        one.tick(now=True)
        token.undeclare()
        return one.stats

    def _run(self, stop: threading.Event) -> None:
        assert self.subs is not None
        cmd_sub, truth_sub, manager = self.subs
        sensors = list(self.sensors)
        waiting: dict[str, _Sensor] = {}  # sensors with commands to answer
        wait_s = self.wait_s
        stages = Stages()
        lap = stages.lap

        def command(s: Sample) -> None:
            key = s.key
            chunk = key.rpartition("/")[2]
            to = [one for one in sensors if one.hears(key, chunk)]
            if to:
                cmd = _command(s)
                enabled = None if isinstance(cmd, msg.WireError) else frozenset(cmd.enabled)
                for one in to:
                    one.accept(cmd, enabled)
                    if one.pending:
                        waiting[one.id] = one

        def truth(s: Sample) -> None:
            tr = _truth(s)
            for one in sensors:
                one.take_truth(tr)

        next_beat = 0
        now_ns = sensors[0].clock.now_ns
        try:
            while not stop.is_set():
                if (t_ns := now_ns()) >= next_beat:  # only the heartbeats that are due
                    for one in sensors:
                        if one.heartbeat.due_ns <= t_ns:
                            one.tick()
                    next_beat = min(one.heartbeat.due_ns for one in sensors)
                if manager.left:
                    for one in sensors:
                        one.stats.manager_lost = manager.crashed
                    break
                lap("heartbeat")
                if waiting:  # waiting for a commanded scan's truth
                    if (t := truth_sub.recv(wait_s)) is not None:
                        truth(t)
                    lap("wait: truth")
                else:
                    s = cmd_sub.recv(timeout=wait_s)
                    lap("wait: command")
                    if s is not None:
                        command(s)
                    lap("command")
                while (s := cmd_sub.try_recv()) is not None:
                    command(s)
                while (t := truth_sub.try_recv()) is not None:
                    truth(t)
                lap("drain")
                for sid in list(waiting):
                    one = waiting[sid]
                    one.answer(lap)
                    if not one.pending:
                        del waiting[sid]
        finally:
            for one in sensors:
                one.tick(now=True)
                if one.token is not None:
                    one.token.undeclare()
            manager.close()
            cmd_sub.close()
            truth_sub.close()
            sent = sum(one.stats.measurements_sent for one in sensors)
            stages.dump(f"sensors-{len(sensors)}", sent=sent)


#: the host loops of this process, by the id of their session (a test may run several)
_hosts: dict[int, HostLoop] = {}
_host_lock = threading.Lock()


def join_host(bus: Bus, ids: list[str], net: NetworkSpec) -> HostLoop:
    """The :class:`HostLoop` of this process's hosted sensors ``ids`` on ``bus`` (their shared
    session), made by the first of them to ask: every :func:`serve` of one of them on a share
    of it joins it."""
    key = id(getattr(bus, "session", None))
    with _host_lock:
        host = _hosts.get(key)
        if host is None or host.bus is not bus:
            host = _hosts[key] = HostLoop(bus, ids, net)
        return host


def process_main(
    args: Any,
    cfg: Any,
    stop: threading.Event,
    run: Callable[[Any, str, Bus, str, Clock, threading.Event], SensorStats],
    wrap: Callable[[Bus], Any] | None = None,
) -> int:
    """A sensor process around its loop: open the client session, run ``run(cfg, id, bus,
    run_id, clock, stop)`` (over ``wrap(bus)`` when given: a bus that emulates the links, say;
    closed afterwards), print the counters, exit 0.  A sensor hosted with others on one
    session (``args.shared_bus``, ``args.host_ids``: :mod:`sensors.host`) is served by their
    one :class:`HostLoop` (unless its links are emulated: ``wrap``)."""
    shared, ids = getattr(args, "shared_bus", None), getattr(args, "host_ids", None)
    if shared is not None and ids is not None and len(ids) > 1 and wrap is None:
        join_host(shared, list(ids), cfg.network)
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
    if stats.manager_lost:
        say(args, not_ended_well(args.run, "this sensor"))
        return EXIT_RUN_FAILED
    return EXIT_OK
