"""Small pieces every node loop (world, sensors, recorder) shares: its heartbeat and its watch
on the manager's liveliness.  Both are driven by the loop itself (``tick``, ``poll``); nothing
here runs on its own thread."""

from __future__ import annotations

import functools
import os
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any

from covnet.clock import Clock
from covnet.config import NetworkSpec
from covnet.errors import NoRun
from covnet.wire import messages as msg
from covnet.wire.bus import Bus


class Heartbeat:
    """Publishes ``Heartbeat(role, node_id, scan, rejected)`` at most every ``period_s``: the
    application-level sign of life a hung loop stops giving (its zenoh session, hence its
    liveliness token, would live on).

    Any message the manager reads from the node is a sign of life too (the manager takes a
    sensor's measurement as one, :meth:`manager.loop.Loop.collect`): a node that published
    one calls :meth:`touch`, and the next heartbeat is due ``period_s`` after that message
    instead.  So the manager still hears from a live node at least every ``period_s`` (the
    failure bound, ``failure_timeout_s`` after the last sign of life, is unchanged), and a
    sensor measuring every scan sends no heartbeat while it does."""

    def __init__(
        self,
        bus: Bus,
        clock: Clock,
        run_id: str,
        role: str,
        node_id: str,
        period_s: float,
        config: str | None = None,
    ) -> None:
        self._bus, self._clock = bus, clock
        self._role, self._node_id, self._config = role, node_id, config
        self._host = host_id()
        self._key = msg.heartbeat_key(run_id, role, node_id)
        self._period_ns = int(period_s * 1e9)
        self._next_ns = 0

    @property
    def due_ns(self) -> int:
        """When (``clock.now_ns``) the next heartbeat is due: a :meth:`tick` before it sends
        nothing."""
        return self._next_ns

    def tick(
        self,
        scan: int,
        rejected: Mapping[str, int] | None = None,
        *,
        sent: int | None = None,
        now: bool = False,
    ) -> bool:
        """Publish a heartbeat if one is due (``now``: at once, as a node leaves); ``sent``:
        a sensor's count of messages sent for the manager.  Returns whether it published."""
        t = self._clock.now_ns()
        if t < self._next_ns and not now:
            return False
        hb = msg.Heartbeat(
            role=self._role,
            node_id=self._node_id,
            scan=scan,
            t_sent_ns=t,
            rejected=dict(rejected) if rejected else None,
            sent=sent,
            config=self._config,
            host=self._host,
        )
        self._bus.publish(self._key, msg.encode(hb))
        self._next_ns = t + self._period_ns
        return True

    def touch(self) -> None:
        """The node just published a message the manager takes as a sign of life: the next
        heartbeat is due one period from now (class docstring)."""
        self._next_ns = self._clock.now_ns() + self._period_ns


MANAGER_GRACE = 3.0
"""How many failure timeouts (``network.failure_timeout_s``) a node waits for a manager whose
token went without its end (:class:`ManagerWatch`) before it takes the run for over."""


WORLD_GONE_WAIT_S = 0.5
"""How long a scan waits for what depends on the truth once the world is down for good (dead,
and not restarted): a node that has the scan's truth answers in milliseconds, one without it
never (a scan waited ``network.scan_timeout_s``, 10 s: a mobile run whose world died at scan 20
of 100 took 13 more minutes; peer nodes then timed each other out and split)."""


NOTE = "note: "
"""A node's output line the user must see without ``--verbose`` starts so (the launcher shows
it: :func:`covnet.processes.up.shown`); the recorder's visual channels cut short by their time
budget said so only with ``--verbose``: a long run's Foxglove view ended at scan 4 731 of 6 000
without a word."""

MANAGER_LOST = "manager_lost"
"""The counter a node loop built on :func:`serve_commands` (the world) sets when it left
because the run did not end well (:attr:`ManagerWatch.crashed`): its process then exits 1
saying so (:func:`not_ended_well`)."""


def not_ended_well(run_id: str, who: str) -> str:
    """The line of a node that left because its run did not end well (its manager failed or
    went away without ending it): a node of another host exited 0 with the lines of a completed
    run when the manager's host died."""
    return (
        f"{NOTE}run {run_id} did not end well: its manager failed or went away without ending "
        f"the run (see the manager's output, on its host); {who} stopped with it"
    )


@functools.cache
def host_id() -> str:
    """This host's identity as its clock sees it: the kernel's boot id (32 hex digits) and the
    process's time namespace, the same in every process of one boot and namespace, so equal
    ids mean one ``CLOCK_MONOTONIC`` (the stamps of the messages, :mod:`covnet.clock`);
    another boot's, another host's, counts from another origin (the hosts' uptimes apart).
    Without ``/proc`` (not Linux): the host name."""
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            boot = f.read().strip().replace("-", "")[:32]
    except OSError:
        return socket.gethostname()[:64] or "host"
    try:  # a time namespace (``unshare --time``) offsets the monotonic clock of its processes
        return f"{boot}-{os.stat('/proc/self/ns/time').st_ino:x}"
    except OSError:
        return boot


def same_clock(host: str | None) -> bool:
    """Whether a node whose heartbeats name ``host`` stamps with this process's clock (None:
    not known yet, taken as one: a node of this host never sent another)."""
    return host is None or host == host_id()


CONFIG_ID_FREE = ("router", "connect", "security")
"""The ``network`` keys that may differ between the hosts of one run (their endpoints, their
certificate and password files), left out of :func:`config_id`."""


_run_clock = "lockstep"


def set_run_clock(realtime: bool, speed: float) -> None:
    """This process's clock options (``--realtime``, ``--speed``), part of :func:`config_id`
    in real time: a sensors' host given another ``--speed`` emulated its links' delays at its
    own speed while the manager paced and timed the scans at its, and the run (33 m of RMSE
    against 7) said ``completed`` at the manager's speed (hunt 12).  Every node process sets it
    as it starts (:func:`covnet.processes.process.resolve_run`); a loop run in a test's
    threads keeps the default, lockstep."""
    global _run_clock
    _run_clock = f"realtime x{speed!r}" if realtime else "lockstep"


def config_id(cfg: Any) -> str:
    """The identity of the config a node runs, run options applied (``--seed``, ``--fusion``,
    ``--solver``; ``--realtime`` and ``--speed``: :func:`set_run_clock`): 16 hex digits of the
    hash of the kind's normalised config without the ``network`` keys of
    :data:`CONFIG_ID_FREE` and without ``allocation.metrics`` (``--metric``: the manager's
    choice of episodes; a sensor measures the same whatever the metric, and the manager's
    episodes are its own).  Every node's heartbeats carry it, and the manager starts only when
    every node's equals its own: hosts given one ``--run`` with a stale copy of the config,
    another seed or another fusion mode ran one mixed network, every host exiting 0 and
    ``run.json`` claiming the manager's config."""
    from covnet.config import hash_of  # start-up: only as a node begins

    data = shared_config(cfg)
    if _run_clock != "lockstep":  # (a lockstep run's identity is its config's alone)
        data = {**data, "run_clock": _run_clock}
    return hash_of(data)[:16]


def shared_config(cfg: Any) -> dict[str, Any]:
    """What every host of one run holds alike: the kind's normalised config without the
    ``network`` keys of :data:`CONFIG_ID_FREE` and without ``allocation.metrics``.  The
    identity :func:`config_id` hashes (with the run's clock), and what the default run id
    (:func:`covnet.processes.process.default_run_id`) is derived from, so that hosts whose
    configs the identity check lets in also meet without ``--run``."""
    from covnet import kinds  # start-up: the kinds' registry, only as a node begins

    data: dict[str, Any] = kinds.of(cfg).normalised(cfg)
    net = data.get("network")
    if isinstance(net, dict):
        data = {**data, "network": {k: v for k, v in net.items() if k not in CONFIG_ID_FREE}}
    alloc = data.get("allocation")
    if isinstance(alloc, dict):
        data = {**data, "allocation": {k: v for k, v in alloc.items() if k != "metrics"}}
    return data


def world_returns(cfg: Any) -> bool:
    """Whether the launcher restarts a world that dies: ``network.restart: on-failure`` and a
    kind whose world may be restarted (its truth the seed's: :meth:`covnet.kinds.Kind.
    restartable`).  Otherwise a dead world is gone for good, and the waits for what depends
    on the truth end after :data:`WORLD_GONE_WAIT_S`."""
    # start-up: the kinds' registry, only as a loop begins
    from covnet import kinds

    return cfg.network.restart == "on-failure" and "world" in kinds.of(cfg).restartable(cfg)


def manager_grace_s(net: NetworkSpec) -> float:
    """:data:`MANAGER_GRACE` failure timeouts, in seconds."""
    return MANAGER_GRACE * net.failure_timeout_s


def manager_appear_s(net: NetworkSpec) -> float:
    """How long a node waits for a manager it has never seen: the manager's own wait for the
    nodes (``ready_timeout_s``) and its grace (:class:`ManagerWatch`'s ``appear_s``)."""
    return net.ready_timeout_s + manager_grace_s(net)


class ManagerWatch:
    """Follows the manager's liveliness.  ``left`` once the run is over for this node: the
    manager declared its end (:func:`~covnet.wire.messages.done_key`: finished or stopped on
    purpose), or a manager that was seen has been gone for ``grace_s`` (a crash).  A manager
    token that goes and comes back within ``grace_s`` (a lossy or slow link can end the zenoh
    session that carries it, while both ends run on) is not the end: the node stays, and the
    manager takes it back when it hears it again.

    ``appear_s``: a manager never seen within that long of the watch's start is not coming
    (another run id: a mistyped ``--run``, or hosts that derived different ones): :attr:`left`
    raises :class:`ConnectionError` saying so (the node's process exits 1 with that line);
    a sensors-only host waited for it without end."""

    def __init__(
        self, bus: Bus, run_id: str, grace_s: float = 0.0, appear_s: float | None = None
    ) -> None:
        self._sub = bus.watch_liveliness(msg.alive_keyexpr(run_id, "manager"))
        self.run_id = run_id
        self.grace_s = grace_s
        self.appear_by = None if appear_s is None else time.monotonic() + appear_s
        self.appear_s = appear_s
        self.seen = False
        self.up = False
        self.done = False
        self.failed = False  # the manager declared the run's end with an error
        self.down_since = 0.0

    def poll(self) -> None:
        while (ev := self._sub.try_recv()) is not None:
            try:
                node = msg.parse_alive_key(ev.key)[1]
            except ValueError:
                continue
            if node in (msg.DONE_ID, msg.FAILED_ID):
                self.done = self.done or ev.alive
                self.failed = self.failed or (ev.alive and node == msg.FAILED_ID)
            elif node == msg.MANAGER_ID:
                self.seen = self.seen or ev.alive
                if self.up and not ev.alive:
                    self.down_since = time.monotonic()
                self.up = ev.alive

    @property
    def left(self) -> bool:
        self.poll()
        if self.done:
            return True
        if not self.seen and self.appear_by is not None and time.monotonic() > self.appear_by:
            raise NoRun(
                f"no manager of run {self.run_id!r} appeared within {self.appear_s:g} s (is "
                "--run the same on every host, and the manager's host started?)"
            )
        return self.seen and not self.up and time.monotonic() - self.down_since >= self.grace_s

    @property
    def crashed(self) -> bool:
        """Whether the run did not end well for this node: the manager declared its end with
        an error (:func:`~covnet.wire.messages.failed_key`: nodes of another config, say), or
        left without declaring it (its process or host failed).  A sensor that leaves for
        that says so and exits 1 (a sensors-only host exited 0, with the lines of a completed
        run, when the manager's host died mid-run)."""
        return self.failed or (self.seen and not self.done and not self.up)

    def left_badly(self, stop: threading.Event) -> bool:
        """Whether the node leaves (not stopped itself) because the run did not end well
        (:attr:`crashed`)."""
        self.poll()
        return not stop.is_set() and self.crashed

    def note_lost(self, counts: Counter[str], stop: threading.Event) -> None:
        """Set ``counts[MANAGER_LOST]`` when :meth:`left_badly` (a world's counters)."""
        if self.left_badly(stop):
            counts[MANAGER_LOST] = 1

    def close(self) -> None:
        self._sub.close()


def serve_commands(
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    net: NetworkSpec,
    role: str,
    node_id: str,
    counts: Counter[str],
    handle: Callable[[msg.Command], bool],
    idle: Callable[[], None] | None = None,
    *,
    config: str | None = None,
) -> None:
    """A node that acts on the manager's commands (the world): subscribe, declare the token,
    then until ``stop`` or the manager leaves: heartbeat, decode each command strictly (a bad
    one counted as ``rejected:<reason>``) and pass it to ``handle``, which returns whether it
    took it (else it counted why).  Heartbeats carry the last scan taken and the rejections.
    ``idle()``, when given, runs before each wait for a command; ``config``: the node's
    :func:`config_id`, in its heartbeats."""
    cmd_sub = bus.subscribe(msg.command_keyexpr(run_id))  # every command
    manager = ManagerWatch(bus, run_id, manager_grace_s(net), manager_appear_s(net))
    token = bus.declare_token(msg.alive_key(run_id, role, node_id))
    heartbeat = Heartbeat(bus, clock, run_id, role, node_id, net.heartbeat_s, config)
    last_scan = 0
    try:
        while not stop.is_set() and not manager.left:
            rejected = {k[9:]: v for k, v in counts.items() if k.startswith("rejected:")}
            heartbeat.tick(last_scan, rejected)
            if idle is not None:
                idle()
            s = cmd_sub.recv(timeout=net.heartbeat_s / 2)
            if s is None:
                continue
            try:
                cmd = msg.decode_command(s.key, s.payload)
            except msg.WireError as exc:
                counts[f"rejected:{exc.reason}"] += 1
                continue
            if handle(cmd):
                last_scan = cmd.scan
    finally:
        manager.note_lost(counts, stop)
        token.undeclare()
        manager.close()
