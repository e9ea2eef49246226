"""THE manager scan skeleton every scenario kind's manager runs, with its maths plugged in.

Per episode ``e`` (the kind's :attr:`ScanLogic.episodes`: one per allocation metric for
covariance control, one for the others) and scan ``k = 1..scans``::

    1. (real time) wait for scan k's time, t_origin + (k - 1) T
    2. the sensors alive: liveliness tokens and heartbeats (:class:`manager.membership.
       Membership`; a sensor's well-formed message on its own key counts as a heartbeat, so a
       sensor that measures sends none, :class:`covnet.processes.node_kit.Heartbeat`);
       failures and rejoins since the last scan go to the kind
    3. the kind decides: enabled set (and its per-sensor modes / targets)       logic.decide
    4. Command(k) on the key that names the enabled set (zenoh takes it to those sensors and
       the recorder only); in lockstep, then scan k-1's report (step 7): the next command is
       what the network waits for, the report only the recorder and observers read
    5. the kind's work that can be done while the sensors measure                logic.ahead
    6. collect scan k's messages from the enabled sensors until all arrived, a sensor failed,
       or the deadline passed (lockstep: ``network.scan_timeout_s``; real time: ``t_k +
       deadline_fraction T``); with the world down for good (dead, and not a world the
       launcher restarts), :data:`WORLD_GONE_WAIT_S` at most: a sensor without the scan's
       truth cannot answer, one with it answers at once.  Anything malformed, from the wrong
       key, for another scan, from a sensor that was not enabled, or that the kind finds
       unusable (logic.usable) is counted by reason and dropped, never fused; a late message
       of an earlier scan goes to the kind (logic.on_late: re-filtered or dropped, counted
       either way)
    7. the kind fuses what arrived (logic.fuse) and reports the scan (logic.report): its
       Track(s) and Status(k) go on the bus, the status and progress hooks are called; at once
       in real time, in lockstep just after Command(k+1) (and at an episode's end, and when the
       loop stops)

The loop takes its bus, clock and stop event from the caller: a test runs it in a thread over
``InMemoryBus``.  What a kind plugs in is the :class:`ScanLogic` protocol
(:mod:`manager.covariance`, :mod:`manager.mobile`, :mod:`manager.passive`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field
from typing import Any, Protocol

from covnet.clock import Clock
from covnet.config import NetworkSpec
from covnet.processes.node_kit import WORLD_GONE_WAIT_S, config_id, same_clock, world_returns
from covnet.processes.runtime_stats import NetStats
from covnet.wire import messages as msg
from covnet.wire.bus import Bus, Sample, dropped
from covnet.wire.codec import decode_many
from covnet.wire.profiling import Stages, profiled
from manager.membership import Membership

__all__ = [
    "Decision",
    "Loop",
    "ManagerError",
    "ScanLogic",
    "ScanReport",
    "run_scans",
    "wait_for_nodes_to_leave",
]

WORLD_ID, RECORDER_ID = msg.WORLD_ID, msg.RECORDER_ID
MEMBERSHIP_POLL_S = 0.005
"""While measurements keep arriving, the longest time between two membership checks."""
MIN_BATCH, MAX_BATCH = 8, 1024
"""Samples taken from the queue at once (:meth:`Loop._take_many`): fewer than ``MIN_BATCH``
are taken one by one (a batch's fixed cost is a few messages' worth: in process, 4 together
cost 19 us a message against 16 one by one, 8 cost 13, 64 cost 7), at most ``MAX_BATCH``."""
MIN_VERDICTS = 16
"""A kind's verdicts on fewer messages than this are asked one by one (numpy's fixed costs)."""


def take_heartbeat(
    stats: NetStats, run_id: str, s: Sample, known: AbstractSet[str]
) -> msg.Heartbeat | None:
    """The node heartbeat in sample ``s`` (already counted as received), checked, its
    rejection counts kept in ``stats.node_rejected``; None when refused, counted by reason (a
    wire error's, ``bad_key``, ``key_mismatch``: another node's key, ``unknown_node``: a node
    not in ``known``).  The manager's loop and the peer observer read heartbeats alike."""
    try:
        hb = msg.decode_as(s.payload, msg.Heartbeat)
        own_key = msg.heartbeat_key(run_id, hb.role, hb.node_id)
    except msg.WireError as exc:
        stats.reject(s.key, exc.reason)
        return None
    except ValueError:
        stats.reject(s.key, "bad_key")
        return None
    if own_key != s.key:
        stats.reject(s.key, "key_mismatch")
        return None
    if hb.node_id not in known:
        stats.reject(s.key, "unknown_node")
        return None
    if hb.rejected:
        stats.node_rejected[hb.node_id] = dict(hb.rejected)
    return hb


CONFIGS_HEARD_S = 1.0
"""After the first heartbeat of another config, how long the manager still listens for the other
nodes' (five heartbeats at the default ``network.heartbeat_s``) before it refuses the run, so that
the refusal names them all (a host's nodes start together), unless every node has spoken."""


class ConfigRefusal:
    """Whether to refuse the run for nodes of another config (:func:`other_configs`): once every
    node has said which config it runs, or :data:`CONFIGS_HEARD_S` after the first heartbeat of
    another config, so that the refusal names every node of the other host heard by then, not
    the first one alone.  The manager's loop and the peer observer refuse alike."""

    def __init__(self) -> None:
        self.first_at: float | None = None  # when a node of another config was first heard

    def why(self, own: str, heard: Mapping[str, str | None], all_heard: bool) -> str | None:
        """The refusal, or None (no other config, or the others' heartbeats still on their
        way)."""
        why = other_configs(own, heard)
        if why is None:
            return None
        now = time.monotonic()
        if self.first_at is None:
            self.first_at = now
        return why if all_heard or now - self.first_at >= CONFIGS_HEARD_S else None


def other_configs(own: str, heard: Mapping[str, str | None]) -> str | None:
    """Why a run must not start: the nodes whose heartbeats named another config than ``own``
    (:func:`~covnet.processes.node_kit.config_id`), or none (a covnet from before heartbeats
    named it: its config and seed cannot be checked, and one was let in unchecked, ending
    ``completed`` with another seed's sensors), else None.  The manager's loop and the peer
    observer check alike."""
    other = {n: c for n, c in heard.items() if c != own}
    if not other:
        return None
    named = {n: c for n, c in other.items() if c is not None}
    unnamed = sorted(n for n, c in other.items() if c is None)
    parts = []
    if named:
        nodes = ", ".join(f"{n} ({c})" for n, c in sorted(named.items()))
        parts.append(
            f"nodes run another config than this manager's ({own}): {nodes}. Every host of a "
            "run must run the same config file with the same run options (--seed, --fusion, "
            "--solver, --realtime, --speed); only network.router, network.connect, "
            "network.security and the metrics (--metric) may differ"
        )
    if unnamed:
        parts.append(
            f"nodes name no config in their heartbeats: {', '.join(unnamed)} (an older covnet "
            "than this manager's, whose config and seed cannot be checked); run the same "
            "covnet on every host"
        )
    return "; ".join(parts)


#: nodes a not-ready message names one by one; the rest are counted
NAMED_NODES = 12


def _some(nodes: Sequence[str]) -> str:
    """``['S1', 'S2']``; beyond :data:`NAMED_NODES` the first ones and how many more."""
    if len(nodes) <= NAMED_NODES:
        return str(list(nodes))
    shown = str(list(nodes[:NAMED_NODES]))[:-1]
    return f"{shown}, ... and {len(nodes) - NAMED_NODES} more ({len(nodes)} in all)]"


def not_ready(timeout_s: float, not_alive: Sequence[str], unheard: Sequence[str]) -> str:
    """Why the network did not become ready within ``timeout_s`` (``network.ready_timeout_s``):
    the nodes whose liveliness token never came up, else those that never said in a heartbeat
    which config they run.  The manager's loop and the peer observer say it alike."""
    wait = f"{timeout_s} s (network.ready_timeout_s)"
    if not_alive:
        return f"nodes not alive after {wait}: {_some(not_alive)}"
    return f"nodes alive but sent no heartbeat within {wait}: {_some(unheard)}"


class ManagerError(RuntimeError):
    """The network could not run (nodes never came up, the stop was requested, ...)."""


class LoopResult(Protocol):
    """What every kind's result holds for the skeleton (and the process around it)."""

    stats: NetStats
    completed: bool
    error: str | None


@dataclass(frozen=True)
class Decision:
    """Step 3: whom scan ``k``'s command enables, with the per-sensor fields some kinds add
    (``modes``, ``targets``, ``windows``: see :class:`covnet.wire.messages.Command`)."""

    enabled: tuple[str, ...]
    modes: dict[str, str] | None = None
    targets: dict[str, tuple[str, ...]] | None = None
    windows: dict[str, Any] | None = None


@dataclass(frozen=True)
class ScanReport:
    """Step 7: what the kind reports of a fused scan: the messages to publish (``tracks`` on
    the track key, ``status`` on the status key) and ``status_info``, the kind's part of the
    status hook's dict (it must hold ``info``: the scan in one line, for the live view)."""

    tracks: Sequence[msg.Track]
    status: msg.Status
    status_info: dict[str, Any]


class ScanLogic(Protocol):
    """The maths a kind plugs into :func:`run_scans` (see the module docstring)."""

    @property
    def result(self) -> Any:
        """The kind's result record (a :class:`LoopResult`), filled as the scans go."""
        ...

    @property
    def episodes(self) -> Sequence[str]: ...

    @property
    def scans(self) -> int: ...

    @property
    def period_s(self) -> float: ...

    @property
    def message_type(self) -> type[msg.Measurement] | type[msg.LocalTrack]:
        """What the sensors send for a scan."""
        ...

    @property
    def accept_unsolicited(self) -> bool:
        """Fuse a message of a sensor that was not enabled (it measured on a stale command)."""
        ...

    def start_episode(self, e: int) -> None: ...

    def membership(self, e: int, k: int, events: list[dict[str, Any]]) -> None:
        """Failures and rejoins seen at scan ``k`` (``sensor``, ``scan``, ``event``, and for a
        failure ``detected_ns``)."""
        ...

    def decide(self, e: int, k: int, failed: frozenset[str]) -> Decision: ...

    def ahead(self, e: int, k: int) -> None:
        """Work for the scan that does not need its messages (done while they travel)."""
        ...

    def usable(self, m: Any) -> bool | str:
        """The kind's test of a message's content (the wire schema checked its form): True,
        or False / the reason it is rejected for (``bad_measurement`` when False).  A kind
        may also have ``usable_many(ms)``: the list of ``usable(m)`` for several messages of
        the current scan at once (optional: the loop looks it up)."""
        ...

    def on_late(self, m: Any) -> bool | None:
        """A late message of an earlier scan of this episode: True re-filtered, False dropped,
        None not for this kind (counted ``late`` and rejected)."""
        ...

    def fuse(self, e: int, k: int, got: dict[str, Any]) -> Any:
        """Fuse what arrived for scan ``k``; returns what :meth:`report` needs."""
        ...

    def report(self, e: int, k: int, fused: Any, failed: frozenset[str]) -> ScanReport:
        """Log scan ``k`` in the result and make its messages (off the critical path)."""
        ...


StatusFn = Callable[[dict[str, Any]], None]


class Loop:
    """The manager's bus side: membership, publishing, collecting; only the skeleton (and the
    peer observer's own loop) drive it."""

    def __init__(
        self, net: NetworkSpec, sensor_ids: tuple[str, ...], bus: Bus, run_id: str, clock: Clock
    ) -> None:
        self.net, self.bus, self.run_id, self.clock = net, bus, run_id, clock
        self.ids = sensor_ids
        self.sensor_set = frozenset(sensor_ids)
        self.members = Membership(
            expected=(*self.ids, WORLD_ID), failure_timeout_ns=int(net.failure_timeout_s * 1e9)
        )
        # the recorder must hear everything: wait for its token too (never allocated)
        self.wait_for = (*self.members.expected, RECORDER_ID) if net.record else ()
        #: the nodes whose heartbeats count (the recorder's for its rejection counts only)
        self.hb_known = frozenset((*self.members.expected, RECORDER_ID))
        self.stats = NetStats()
        # the failed set as the run's counts last saw it (an episode's own starts afresh)
        self._counted_failed: frozenset[str] = frozenset()
        #: the scan loop's time by stage (``covnet bench up --profile``; off by default)
        self.stages = Stages()
        # slow links: a late message goes to on_late (re-filtered or dropped, it says which);
        # a sensor that measured on a stale command is fused too
        self.on_late: Callable[[Any], bool | None] | None = None
        self.accept_unsolicited = False
        # the sensors the scan being collected enabled (a sensor dropped from the wait as
        # failed is still one: its measurement arriving before the scan is fused is taken)
        self._enabled: frozenset[str] = frozenset()
        #: slow links: collect until the deadline (a late message that arrives before it is
        #: re-filtered before the scan is fused, as covnet run does)
        self.to_deadline = False
        #: the launcher restarts a world that dies (``network.restart: on-failure`` and a kind
        #: whose world may be restarted): a scan then waits for it as for anything else
        self.world_returns = False
        self._looked_ns: int | None = None  # the last poll_membership
        self._vital_down: dict[str, dict[str, Any]] = {}  # note_vital
        #: this manager's :func:`~covnet.processes.node_kit.config_id` (None: not compared), and
        #: the one each node's heartbeats carry
        self.config_id: str | None = None
        self.node_configs: dict[str, str | None] = {}
        self._refusal = ConfigRefusal()
        #: the nodes whose heartbeats name another clock than this process's
        #: (:func:`~covnet.processes.node_kit.same_clock`): their latencies are not taken
        self.other_clock: set[str] = set()
        self.meas_sub = bus.subscribe(msg.measurement_keyexpr(run_id))
        # each sensor's own measurement key (what parse_measurement_key gives for it)
        self._key_sensor = {msg.measurement_key(run_id, sid): sid for sid in sensor_ids}
        self.hb_sub = bus.subscribe(msg.heartbeat_keyexpr(run_id))
        self.live_sub = bus.watch_liveliness(msg.alive_keyexpr(run_id))
        self.token = bus.declare_token(msg.alive_key(run_id, "manager", msg.MANAGER_ID))
        # the run's end declared (:meth:`end`), or by another session while the run goes on
        self.ending = self.forged_done = False
        self.keys = {
            "cmd": msg.command_keyexpr(run_id),  # commands are counted under this one
            "track": msg.track_key(run_id),
            "status": msg.status_key(run_id),
        }

    def end(self, failed: bool = False) -> None:
        """The run is over on purpose: declare its end (the nodes leave at once; a manager
        token lost without it is waited for, :class:`covnet.processes.node_kit.
        ManagerWatch`), then withdraw the manager's token.  ``failed``: the run ended with an
        error (:func:`~covnet.wire.messages.failed_key`: the nodes leave saying so)."""
        self.ending = True
        key = msg.failed_key(self.run_id) if failed else msg.done_key(self.run_id)
        self.done_token = self.bus.declare_token(key)
        self.token.undeclare()

    # ---- bus helpers --------------------------------------------------------------------

    def publish(self, key: str, message: msg.Message, *, count_as: str | None = None) -> None:
        """Encode and publish ``message`` on ``key``; counted under ``count_as`` or ``key``."""
        payload = msg.encode(message)
        self.bus.publish(key, payload)
        self.stats.sent(count_as or key, len(payload))

    def publish_command(self, cmd: msg.Command) -> None:
        """Publish ``cmd`` on its own key (:func:`~covnet.wire.messages.command_key`: zenoh takes
        it to the enabled sensors only); counted under ``keys["cmd"]``, every command's."""
        key = msg.command_key(self.run_id, cmd.enabled)
        self.publish(key, cmd, count_as=self.keys["cmd"])

    def poll_membership(self) -> None:
        """Drain liveliness events and heartbeats (non-blocking); after a look more than the
        failure timeout after the last one (this process was paused), the nodes get two
        heartbeat periods to be heard (:meth:`manager.membership.Membership.resumed`)."""
        now = self.clock.now_ns()
        last_look, self._looked_ns = self._looked_ns, now
        while (ev := self.live_sub.try_recv()) is not None:
            try:
                role, node = msg.parse_alive_key(ev.key)
            except ValueError:
                self.stats.reject(ev.key, "bad_key")
                continue
            if role in ("sensor", "world", "recorder"):
                self.members.token(node, ev.alive, now)
            elif (
                role == "manager"
                and node in (msg.DONE_ID, msg.FAILED_ID)
                and ev.alive
                and not self.ending
            ):
                self.stats.reject(ev.key, "forged_done")
                self.forged_done = True
        while (s := self.hb_sub.try_recv()) is not None:
            self.stats.received(s.key, len(s.payload))
            hb = take_heartbeat(self.stats, self.run_id, s, self.hb_known)
            if hb is not None:
                self.node_configs.setdefault(hb.node_id, hb.config)
                if same_clock(hb.host):
                    self.other_clock.discard(hb.node_id)
                else:
                    self.other_clock.add(hb.node_id)
                if self.config_id is not None and hb.config != self.config_id:
                    # another config's node (a host restarted with another copy, a restart
                    # that read an edited file; an older covnet's, which names none): down,
                    # and nothing it sends is a sign of life or fused until it names ours
                    self.stats.reject(s.key, "config_mismatch")
                    self.members.refuse(hb.node_id)
                    continue
                self.members.accept(hb.node_id)
            if hb is not None and hb.node_id != RECORDER_ID:
                self.members.heartbeat(hb.node_id, now)
                if hb.sent is not None and hb.role == "sensor":
                    self.stats.reported(hb.node_id, hb.sent)
        if last_look is not None and now - last_look > self.members.failure_timeout_ns:
            self.members.resumed(last_look, now, int(2e9 * self.net.heartbeat_s))

    def membership_changes(
        self, k: int, previous: frozenset[str]
    ) -> tuple[frozenset[str], list[dict[str, Any]]]:
        """The failed set at scan ``k`` and the failure/rejoin events since ``previous``
        (a failure carries when it was first seen, ``detected_ns``).  Another session's
        declaration of the run's end (the ``done`` token, which this manager declares only as
        it ends) makes every node leave: the run stops here, saying so."""
        self.poll_membership()
        if self.forged_done:
            raise ManagerError(
                f"scan {k}: another session declared the run's end (the liveliness token "
                f"{msg.done_key(self.run_id)}, which only this manager declares, as it ends): "
                "every node leaves; without access control any session on the bus can end "
                "a run (README: Security (multi-host runs))"
            )
        failed = self.members.failed(self.clock.now_ns())
        events: list[dict[str, Any]] = []
        for sid in sorted((failed ^ previous) - {WORLD_ID}):
            event: dict[str, Any] = {
                "sensor": sid,
                "scan": k,
                "event": "failed" if sid in failed else "rejoined",
            }
            if sid in failed:
                event["detected_ns"] = self.members.down_since_ns(sid)
            events.append(event)
        # the run's counts: each change once (every episode's log starts from no failure, so
        # the same failure is an event of each episode; it was counted once an episode)
        for sid in sorted((failed ^ self._counted_failed) - {WORLD_ID}):
            self.stats.membership[sid]["failed" if sid in failed else "rejoined"] += 1
        self._counted_failed = failed
        return failed, events

    def note_vital(self, episode: str, last_scan: int, failed: frozenset[str]) -> None:
        """Follow the world and the recorder, which no decision needs but a complete run does:
        the first time each is seen down (``failed`` holds the world; the recorder's token is
        gone) after scan ``last_scan`` of ``episode``, until it is up again.  What is still
        down at the end is :attr:`NetStats.gone_at_end`: a world or recorder of another host
        that died went unreported (its launcher does not watch the manager's run), and the
        manager's host said ``completed``."""
        down = {WORLD_ID} & failed
        if self.net.record and RECORDER_ID not in self.members.alive_tokens:
            down.add(RECORDER_ID)
        for node in down:
            self._vital_down.setdefault(node, {"after_scan": last_scan, "episode": episode})
        for node in set(self._vital_down) - down:
            del self._vital_down[node]

    def vital_gone_at_end(self, episode: str, last_scan: int) -> None:
        """After the last scan: the world or recorder down now (:meth:`note_vital`)."""
        self.poll_membership()
        self.note_vital(episode, last_scan, self.members.failed(self.clock.now_ns()))
        self.stats.gone_at_end = {n: dict(v) for n, v in sorted(self._vital_down.items())}

    def linger(self, timeout_s: float, stop: threading.Event) -> None:
        """After the run (our token gone): keep reading heartbeats, whose ``sent`` counts say
        how many messages each sensor sent in the end and whose ``rejected`` counts say what
        the recorder refused to the end (a repeated Status is known only once the manager's
        last Status has been recorded), until every sensor and the recorder have left,
        ``stop`` or ``timeout_s``.  Measurements arriving now are not taken: the run is over."""
        leaving = (*self.ids, RECORDER_ID) if self.net.record else self.ids
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not stop.is_set():
            self.poll_membership()
            if not any(s in self.members.alive_tokens for s in leaving):
                self.poll_membership()  # a heartbeat sent just before its token went
                return
            stop.wait(0.02)

    def traffic(self) -> tuple[int, int]:
        """Messages and bytes this manager has sent and received so far."""
        st = self.stats
        return (
            sum(st.recv_msgs.values()) + sum(st.sent_msgs.values()),
            sum(st.recv_bytes.values()) + sum(st.sent_bytes.values()),
        )

    def wait_ready(self, stop: threading.Event) -> None:
        """Until every node's liveliness token is up and, with :attr:`config_id` set, every
        node has said in a heartbeat which config it runs: one of another config is refused
        (:class:`ManagerError` naming it and both identities), as is the wait past
        ``ready_timeout_s``."""
        deadline = time.monotonic() + self.net.ready_timeout_s
        while True:
            self.poll_membership()
            missing = [n for n in self.wait_for if n not in self.members.alive_tokens]
            missing = missing or self.members.missing_tokens()
            unheard: list[str] = []
            if self.config_id is not None:
                unheard = [n for n in (self.wait_for or self.members.expected)
                           if n not in self.node_configs]  # fmt: skip
                self._check_configs(unheard)
            if not missing and not unheard:
                return
            if stop.is_set():
                raise ManagerError("stopped before the network was ready")
            if time.monotonic() > deadline:
                raise ManagerError(not_ready(self.net.ready_timeout_s, missing, unheard))
            ev = self.live_sub.recv(timeout=0.05)
            if ev is not None:
                try:
                    role, node = msg.parse_alive_key(ev.key)
                except ValueError:  # a token no node of ours declares
                    self.stats.reject(ev.key, "bad_key")
                    continue
                if role in ("sensor", "world", "recorder"):
                    self.members.token(node, ev.alive, self.clock.now_ns())

    def _check_configs(self, unheard: Sequence[str]) -> None:
        """Refuse the run when a node's heartbeat named another config than this manager's
        (:meth:`wait_ready`), when :class:`ConfigRefusal` says so."""
        assert self.config_id is not None
        if (why := self._refusal.why(self.config_id, self.node_configs, not unheard)) is not None:
            raise ManagerError(why)

    # ---- step 6 -------------------------------------------------------------------------

    def collect(
        self,
        episode: int,
        k: int,
        waiting: set[str],
        deadline: float,
        stop: threading.Event,
        usable: Callable[[Any], bool | str],
        kind: type[msg.Measurement] | type[msg.LocalTrack] = msg.Measurement,
        usable_many: Callable[[Sequence[Any]], list[bool | str]] | None = None,
    ) -> dict[str, Any]:
        """Receive scan ``k``'s messages (measurements, or local tracks: ``kind``) from the
        ``waiting`` sensors until all arrived, a sensor failed or the deadline passed (step 6
        of the module docstring); ``usable`` is the kind's test of a message's content.  On
        slow links (``to_deadline``) until the deadline in any case: a late message of an
        earlier scan that arrives before it is re-filtered before scan ``k`` is fused, as
        ``covnet run`` does (it was left to the next scan once every enabled sensor had
        answered, and the estimates differed).

        Membership (a waiting sensor that failed) is checked whenever a wait times out (at
        least every 0.05 s) and otherwise at most every :data:`MEMBERSHIP_POLL_S`: the scan
        began with a check, and a failed sensor sends nothing, so a wait then times out.
        What is queued is taken together (:meth:`_take_many`; ``usable_many``: the kind's
        verdicts on several messages at once, :meth:`ScanLogic.usable_many`)."""
        got: dict[str, Any] = {}
        self._enabled = frozenset(waiting)
        lap = self.stages.lap
        t_begin = time.monotonic()
        next_poll = time.monotonic() + MEMBERSHIP_POLL_S
        to_deadline = self.to_deadline
        while waiting or to_deadline:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or stop.is_set():
                self.stats.missing_at_deadline += len(waiting)
                break
            s = self.meas_sub.recv(timeout=min(0.05, remaining))
            lap("collect: wait")
            if s is not None:
                batch = [s]  # and whatever else is queued: decoded and checked together
                while len(batch) < MAX_BATCH and (s := self.meas_sub.try_recv()) is not None:
                    batch.append(s)
                lap("collect: wait")
                self._take_many(batch, episode, k, waiting, got, usable, kind, usable_many)
                lap("collect: take")
                if time.monotonic() < next_poll:
                    continue
            next_poll = time.monotonic() + MEMBERSHIP_POLL_S
            self.poll_membership()
            now_ns = self.clock.now_ns()
            dead = {sid for sid in waiting if not self.members.is_up(sid, now_ns)}
            if (
                waiting
                and not to_deadline  # (collected to the deadline anyway: counted there)
                and not self.world_returns
                and time.monotonic() - t_begin > WORLD_GONE_WAIT_S
                and not self.members.is_up(WORLD_ID, now_ns)
            ):
                dead = set(waiting)  # the world is gone: no truth comes for them
            if dead:
                self.stats.missing_at_deadline += len(dead)
                waiting -= dead
            lap("collect: membership")
        # anything else already queued for this scan (duplicates, strays) is judged now
        while (s := self.meas_sub.try_recv()) is not None:
            self._take(s, episode, k, set(), got, usable, kind)
        lap("collect: take")
        return got

    def _take_many(
        self,
        batch: list[Sample],
        episode: int,
        k: int,
        waiting: set[str],
        got: dict[str, Any],
        usable: Callable[[Any], bool | str],
        kind: type[msg.Measurement] | type[msg.LocalTrack],
        usable_many: Callable[[Sequence[Any]], list[bool | str]] | None,
    ) -> None:
        """:meth:`_take` of each sample of ``batch`` in turn, with the same outcome (the same
        counts, rejections by reason, messages taken, in the same order): the payloads the
        wire's batch decoder takes (:func:`covnet.wire.codec.decode_many`, the message
        :func:`~covnet.wire.codec.decode_as` gives) are decoded together, and the kind's
        verdicts on those of this scan come from ``usable_many`` (the verdicts ``usable``
        gives, for several messages at once) when the kind has it; every other sample takes
        :meth:`_take` itself.  A verdict is a function of the message and the scan's plan
        alone, so judging a message before the ones ahead of it are taken changes nothing.
        The messages of a batch are heard (their sensors' sign of life) when it is taken: one
        clock reading for the batch, earlier than one per message by at most the batch's
        handling (a millisecond or two, against failure timeouts of seconds)."""
        if len(batch) < MIN_BATCH:
            for s in batch:
                self._take(s, episode, k, waiting, got, usable, kind)
            return
        decoded = decode_many([s.payload for s in batch], kind)
        verdicts: dict[int, bool | str] = {}
        if usable_many is not None and len(batch) >= MIN_VERDICTS:
            mine = [
                (i, m)
                for i, m in enumerate(decoded)
                if m is not None and m.scan == k and m.episode == episode
            ]
            if mine:
                verdicts = dict(
                    zip([i for i, _ in mine], usable_many([m for _, m in mine]), strict=True)
                )
        keys = self._key_sensor
        now = self.clock.now_ns()
        for i, (s, m) in enumerate(zip(batch, decoded, strict=True)):
            key_sensor = None if m is None else keys.get(s.key)
            if m is None or key_sensor is None or key_sensor != m.sensor_id:
                self._take(s, episode, k, waiting, got, usable, kind)
                continue
            self.stats.received(s.key, len(s.payload))
            if key_sensor in self.members.refused:  # its heartbeats name another config
                self.stats.reject(s.key, "config_mismatch")
                continue
            self.members.heartbeat(key_sensor, now)
            verdict = verdicts.get(i)
            self._judge(s, m, episode, k, waiting, got, usable if verdict is None else verdict)

    def _take(
        self,
        s: Sample,
        episode: int,
        k: int,
        waiting: set[str],
        got: dict[str, Any],
        usable: Callable[[Any], bool | str],
        kind: type[msg.Measurement] | type[msg.LocalTrack] = msg.Measurement,
    ) -> None:
        self.stats.received(s.key, len(s.payload))
        try:
            m = msg.decode_as(s.payload, kind)
            key_sensor = msg.parse_measurement_key(s.key)
        except msg.WireError as exc:
            self.stats.reject(s.key, exc.reason)
            return
        except ValueError:
            self.stats.reject(s.key, "bad_key")
            return
        if key_sensor != m.sensor_id:
            self.stats.reject(s.key, "key_mismatch")
            return
        if key_sensor not in self.sensor_set:  # no sensor of the run: no numbers, no fusion
            self.stats.reject(s.key, "unknown_sensor")
            return
        if key_sensor in self.members.refused:  # its heartbeats name another config
            self.stats.reject(s.key, "config_mismatch")
            return
        self.members.heartbeat(key_sensor, self.clock.now_ns())  # a sensor's sign of life
        self._judge(s, m, episode, k, waiting, got, usable)

    def _latency(self, s: Sample, m: Any) -> None:
        """``m``'s one-way latency (its send to this loop's taking it), when its sender stamps
        with this process's clock (:func:`~covnet.processes.node_kit.same_clock`); a sensor on
        another host is counted instead (its monotonic clock counts from its own boot: a
        sensors' host an hour younger gave a p50 of -3 599 999 ms)."""
        if m.sensor_id in self.other_clock:
            self.stats.meas_latency_other_clock += 1
        else:
            self.stats.meas_latency_ns.append(s.t_recv_ns - m.t_sent_ns)

    def _judge(
        self,
        s: Sample,
        m: Any,
        episode: int,
        k: int,
        waiting: set[str],
        got: dict[str, Any],
        usable: Callable[[Any], bool | str] | bool | str,
    ) -> None:
        """The rest of :meth:`_take` for a well-formed message ``m`` from its sensor's own
        key: its number, lateness, scan, and the kind's verdict (``usable``: the kind's test,
        or its verdict on ``m`` already given).  A message of a scan ahead of this one is
        refused before its number or the sensor's counts see it (no sensor sends one: a
        forgery's ``seq`` would count as sent and lost; it is counted under its key)."""
        at = (m.episode, m.scan)
        if at > (episode, k):
            self.stats.reject(s.key, "wrong_scan")
            return
        if (bad := self.stats.arrived(m.sensor_id, m.seq, at)) is not None:
            self.stats.reject(s.key, bad)
            return
        outcome = self.stats.outcome[m.sensor_id]
        if at < (episode, k):
            self.stats.late += 1
            outcome["late"] += 1
            self._latency(s, m)
            done = (
                self.on_late(m)
                if self.on_late is not None
                and m.episode == episode
                and _passes(usable(m) if callable(usable) else usable)
                else None
            )
            if done is None:
                self.stats.reject(s.key, "late")
            elif done:
                self.stats.late_refiltered += 1
                outcome["late_refiltered"] += 1
            else:
                self.stats.late_dropped += 1
                outcome["late_dropped"] += 1
            return
        reason = None  # (this scan's from here on: a later one was refused, an earlier is late)
        if m.sensor_id in got:
            reason = "duplicate"
        elif (
            m.sensor_id not in waiting
            and m.sensor_id not in self._enabled
            and not self.accept_unsolicited
        ):
            # (an enabled sensor that the wait dropped as failed, and that answered after
            # all, is taken: it was refused as not enabled, one of an honest scan's answers)
            reason = "not_enabled"
        elif not _passes(verdict := usable(m) if callable(usable) else usable):
            reason = verdict if isinstance(verdict, str) else "bad_measurement"
        if reason is not None:
            self.stats.reject(s.key, reason)
            outcome["rejected"] += 1
            return
        self.stats.unsolicited += m.sensor_id not in waiting and m.sensor_id not in self._enabled
        outcome["on_time"] += 1
        got[m.sensor_id] = m
        waiting.discard(m.sensor_id)
        self._latency(s, m)


def _passes(verdict: bool | str) -> bool:
    """A kind's :meth:`ScanLogic.usable` said yes (a string is a reason for no)."""
    return not isinstance(verdict, str) and bool(verdict)


@dataclass
class _Held:
    """A fused scan waiting for its report (step 7)."""

    episode: int
    k: int
    fused: Any
    failed: frozenset[str]
    latency_ns: int  # command published -> scan fused


@dataclass
class _Reporter:
    """Step 7: :meth:`hold` keeps a fused scan, :meth:`run` reports it (the kind's log row and
    messages, then the hooks).  None of it is on the path to the next command."""

    logic: ScanLogic
    loop: Loop
    on_status: StatusFn | None
    on_progress: Callable[[Any, bool], None] | None
    _held: _Held | None = field(default=None)

    def hold(self, held: _Held) -> None:
        self._held = held

    def run(self) -> None:
        h, self._held = self._held, None
        if h is None:
            return
        loop, logic = self.loop, self.logic
        out = logic.report(h.episode, h.k, h.fused, h.failed)
        for track in out.tracks:
            loop.publish(loop.keys["track"], track)
        loop.publish(loop.keys["status"], out.status)
        if self.on_status is not None:
            messages, n_bytes = loop.traffic()
            self.on_status(
                {
                    "metric": logic.episodes[h.episode],
                    "episode": h.episode,
                    "scan": h.k,
                    "scans": logic.scans,
                    "enabled": list(out.status.enabled),
                    "fused": sorted(out.status.fused or ()),
                    "failed": sorted(h.failed - {WORLD_ID}),
                    "latency_ms": h.latency_ns / 1e6,
                    "messages": messages,
                    "bytes": n_bytes,
                    **out.status_info,
                }
            )
        if self.on_progress is not None:
            self.on_progress(logic.result, h.k == logic.scans)


def run_scans(
    logic: ScanLogic,
    loop: Loop,
    stop: threading.Event,
    *,
    realtime: bool = False,
    on_ready: Callable[[], None] | None = None,
    on_status: StatusFn | None = None,
    on_progress: Callable[[Any, bool], None] | None = None,
    linger_s: float = 0.0,
) -> Any:
    """Run every episode of ``logic`` over ``loop``'s bus (module docstring); returns the
    kind's result: also when stopped (``completed=False``) or when the network never came up
    or could not go on (``error`` set).  ``on_progress(result, episode_done)`` is called after
    every scan's report.  ``linger_s``: afterwards, up to that long for the sensors' last
    counts (:meth:`Loop.linger`)."""
    with profiled("manager"):
        return _run_scans(
            logic, loop, stop, realtime=realtime, on_ready=on_ready, on_status=on_status,
            on_progress=on_progress, linger_s=linger_s,
        )  # fmt: skip


def _run_scans(
    logic: ScanLogic,
    loop: Loop,
    stop: threading.Event,
    *,
    realtime: bool,
    on_ready: Callable[[], None] | None,
    on_status: StatusFn | None,
    on_progress: Callable[[Any, bool], None] | None,
    linger_s: float,
) -> Any:
    result, clock, net = logic.result, loop.clock, loop.net
    report = _Reporter(logic, loop, on_status, on_progress)
    lap = loop.stages.lap
    try:
        try:
            loop.wait_ready(stop)
        except ManagerError as exc:
            result.error = str(exc)
            return result
        if on_ready is not None:
            on_ready()
        t_loop = time.perf_counter_ns()
        loop.stages.start()
        for e in range(len(logic.episodes)):
            logic.start_episode(e)
            loop.on_late = logic.on_late
            loop.accept_unsolicited = logic.accept_unsolicited
            # optional: slow links, in real time (in lockstep nothing is late: collecting to
            # the deadline made every scan of a --netns run with link delays scan_timeout_s)
            loop.to_deadline = realtime and bool(getattr(logic, "slow", False))
            t_origin = clock.now()
            failed_prev: frozenset[str] = frozenset()
            for k in range(1, logic.scans + 1):
                if stop.is_set():
                    return result
                if realtime:
                    pace(clock, t_origin + (k - 1) * logic.period_s, stop)
                    if stop.is_set():  # interrupted while waiting for the scan's time
                        return result
                t_core0 = time.perf_counter_ns()
                lap("other")
                failed, events = loop.membership_changes(k, failed_prev)
                if events:
                    logic.membership(e, k, events)
                failed_prev = failed
                loop.note_vital(logic.episodes[e], k - 1, failed)
                lap("membership")
                decision = logic.decide(e, k, failed)
                lap("decide")
                core_ns = time.perf_counter_ns() - t_core0
                t_sent = clock.now_ns()
                cmd = msg.Command(
                    scan=k,
                    t=k * logic.period_s,
                    enabled=decision.enabled,
                    t_sent_ns=t_sent,
                    episode=e,
                    modes=decision.modes,
                    targets=decision.targets,
                    windows=decision.windows,
                )
                loop.publish_command(cmd)
                lap("command")
                report.run()  # scan k-1's (lockstep)
                lap("report")
                logic.ahead(e, k)
                lap("ahead")
                if realtime:
                    deadline = time.monotonic() + net.deadline_fraction * logic.period_s / speed(
                        clock
                    )
                else:
                    deadline = time.monotonic() + net.scan_timeout_s
                got = loop.collect(
                    e,
                    k,
                    set(decision.enabled),
                    deadline,
                    stop,
                    logic.usable,
                    logic.message_type,
                    getattr(logic, "usable_many", None),  # optional: a kind's batch verdicts
                )
                if stop.is_set():
                    # interrupted while collecting: the scan is not done (fused from what had
                    # come, it was recorded as a scan without its measurements)
                    return result
                t_core1 = time.perf_counter_ns()
                fused = logic.fuse(e, k, got)
                lap("fuse")
                loop.stats.core_ns.append(core_ns + time.perf_counter_ns() - t_core1)
                loop.stats.scans_done += 1
                loop.stats.loop_wall_ns = time.perf_counter_ns() - t_loop
                t_fused = clock.now_ns()
                loop.stats.scan_latency_ns.append(t_fused - t_sent)
                report.hold(_Held(e, k, fused, failed, t_fused - t_sent))
                if realtime:
                    report.run()
            report.run()  # the episode's last scan
        if logic.episodes:
            loop.vital_gone_at_end(logic.episodes[-1], logic.scans)
        result.completed = True
    except ManagerError as exc:
        result.error = str(exc)
    finally:
        report.run()  # a stopped loop's last scan
        loop.stages.dump("manager", scans=loop.stats.scans_done)
        loop.end(failed=result.error is not None)
        if linger_s > 0:
            loop.linger(linger_s, stop)
        loop.stats.dropped = dropped(loop.bus)
    return result


def run(
    make_logic: Callable[[Any, Loop], ScanLogic],
    cfg: Any,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    *,
    realtime: bool = False,
    on_ready: Callable[[], None] | None = None,
    on_status: StatusFn | None = None,
    on_progress: Callable[[Any, bool], None] | None = None,
    linger_s: float = 0.0,
) -> Any:
    """A kind's manager over ``bus``: ``make_logic(cfg, loop)`` (the kind's :class:`ScanLogic`)
    in :func:`run_scans`; returns the kind's result (also when stopped, with
    ``completed=False``, or when the network never came up, with ``error`` set)."""
    loop = Loop(cfg.network, cfg.sensor_ids, bus, run_id, clock)
    loop.world_returns = world_returns(cfg)
    loop.config_id = config_id(cfg)
    return run_scans(
        make_logic(cfg, loop),
        loop,
        stop,
        realtime=realtime,
        on_ready=on_ready,
        on_status=on_status,
        on_progress=on_progress,
        linger_s=linger_s,
    )


def wait_for_nodes_to_leave(
    bus: Bus,
    run_id: str,
    timeout_s: float,
    stop: threading.Event,
    expected: Collection[str] = (),
) -> None:
    """After the run: wait (bounded) until no other node of the run is alive, and every node
    of ``expected`` (ids) has come and gone: a run that ended before every node joined (one of
    another config refused) keeps its router up for the late ones to hear its end, as they
    leave at once (they found no router and tried it for ``ready_timeout_s``).  The manager's
    own tokens (its ``done`` or ``failed``, declared to the end for nodes that come late) are
    not waited for: every network run waited the whole ``timeout_s`` (5 s) for them."""
    watch = bus.watch_liveliness(msg.alive_keyexpr(run_id))
    own = msg.alive_keyexpr(run_id, "manager").removesuffix("*")  # covnet/<run>/alive/manager/
    unseen = set(expected)
    alive: set[str] = set()
    deadline = time.monotonic() + timeout_s
    first = True
    while time.monotonic() < deadline and not stop.is_set():
        ev = watch.recv(timeout=0.05)
        if ev is not None:
            if ev.key.startswith(own):
                pass
            elif ev.alive:
                alive.add(ev.key)
                unseen.discard(ev.key.rsplit("/", 1)[-1])
            else:
                alive.discard(ev.key)
            first = False
            continue
        if not alive and not unseen and not first:
            break
        first = False
    watch.close()


def pace(clock: Clock, t: float, stop: threading.Event) -> None:
    """Wait until scenario time ``t`` on a wall clock, waking for ``stop``; a simulated
    clock just jumps."""
    if not hasattr(clock, "speed"):
        clock.sleep_until(t)
        return
    while not stop.is_set():
        remaining = (t - clock.now()) / speed(clock)
        if remaining <= 0:
            return
        stop.wait(min(remaining, 0.05))


def speed(clock: Clock) -> float:
    """A wall clock's speed factor (1 for a clock that has none)."""
    return float(getattr(clock, "speed", 1.0))
