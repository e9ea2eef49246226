"""``covnet run``'s driver: THE in-process scan loop of the covariance-control kind.

It steps the kind's one scan logic (:class:`~covnet.covariance_control.engine.ScanEngine`)
with the sensors' answers handed over in this process, per scan ``k``::

    plan        = engine.decide(k)
    late, got   = transport.exchange(plan)     the enabled sensors' messages of scan k (and,
                                               over slow links, late ones of earlier scans)
    for m in late: transport.late(engine.insert_late(m))        (if engine.usable(m))
    got         = the usable ones (the manager's test, validation gate included)
    engine.record(plan, engine.fuse(plan, got), got)      (the log row; the outcome's
                                               messages are the network's)

The transport is :class:`Direct` (every enabled sensor's message arrives at once) or, when
``network.latency`` is not ideal, :class:`SlowLinks` (the protocol of
:mod:`covnet.covariance_control.links` in simulated time).  The manager process steps the
same engine over zenoh (:mod:`manager.covariance`), the replay with the recording's messages
(:mod:`covnet.covariance_control.replay`): one logic, three drivers.  In peer mode (no
centre) the engine fuses for every node; the transport is the same.
"""

from __future__ import annotations

import heapq
import itertools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from covnet.covariance_control.config import Scenario
from covnet.covariance_control.engine import Plan, ScanEngine, SensorSide

if TYPE_CHECKING:
    from covnet.covariance_control.links import LatencyCounts

__all__ = ["Direct", "InProcessRun", "SlowLinks", "Transport", "run", "run_engine"]


class Transport(Protocol):
    """How the sensors' messages reach the engine in process (module docstring)."""

    def exchange(self, plan: Plan) -> tuple[list[Any], dict[str, Any]]:
        """Scan ``plan.k``'s late messages (of earlier scans) and on-time ones (sensor id ->
        message, ascending sensor index)."""
        ...

    def late(self, refiltered: bool) -> None:
        """What became of a late message."""
        ...

    def finish(self) -> LatencyCounts | None:
        """The episode is over: what the links did (None: nothing to count)."""
        ...


class Direct:
    """Every enabled sensor answers at once and its message arrives on time."""

    def __init__(self, engine: ScanEngine, episode: int) -> None:
        self.episode = episode
        self.sensors = [SensorSide(engine, j) for j in range(len(engine.ids))]

    def exchange(self, plan: Plan) -> tuple[list[Any], dict[str, Any]]:
        got: dict[str, Any] = {}
        for j in sorted(plan.subset):
            m = self.sensors[j].respond(self.episode, plan.k, plan)
            if m is not None:
                got[m.sensor_id] = m
        return [], got

    def late(self, refiltered: bool) -> None:  # pragma: no cover - nothing is late
        pass

    def finish(self) -> None:
        return None


@dataclass
class _Receiver:
    """A sensor's view of the commands: the newest it acted on, and whether it was on."""

    newest: int = 0
    last_on: bool = False


class SlowLinks:
    """The slow, lossy links of ``network.latency`` in simulated time, for one episode of
    ``engine`` (the protocol of :mod:`covnet.covariance_control.links`): per scan the command
    down every link at ``t_k``, the sensors acting on what reaches them (a missed command's
    fallback too), their answers up their links; at ``d_k`` the late messages and the on-time
    ones; :meth:`finish`, what the links did."""

    def __init__(self, engine: ScanEngine, episode: int) -> None:
        # start-up: the link model and helpers only for slow links
        from covnet.core.delay import DOWN, UP, LinkState, link_stream, measures_on_missed
        from covnet.covariance_control.links import LatencyCounts, link_specs

        self.measures_on_missed = measures_on_missed

        sc = engine.sc
        self.engine, self.episode = engine, episode
        self.lat = sc.network.latency
        self.T, self.delta = engine.period_s, sc.network.deadline_fraction
        up_specs, down_specs = link_specs(sc)
        self.up = [LinkState(s, link_stream(sc.seed, j, UP)) for j, s in enumerate(up_specs)]
        self.down = [LinkState(s, link_stream(sc.seed, j, DOWN)) for j, s in enumerate(down_specs)]
        n = len(engine.ids)
        self.sensors = [SensorSide(engine, j) for j in range(n)]
        self.receivers = [_Receiver() for _ in range(n)]
        self.counts = LatencyCounts()
        self.seq = itertools.count()
        self.commands: list[tuple[float, int, int, int]] = []  # heap: (arrival, seq, j, scan)
        self.pending: list[tuple[float, int, int, int, Any]] = []  # (arrival, seq, scan, j, m)
        self.plans: dict[int, Plan] = {}
        self.sent_for = np.zeros(engine.scans + 1, dtype=np.int64)  # messages sent per scan
        self.on_time_for = np.zeros(engine.scans + 1, dtype=np.int64)

    def _send(self, j: int, scan: int, at: float, plan: Plan | None) -> None:
        """Sensor ``j`` measures scan ``scan`` at time ``at`` and sends it up its link."""
        m = self.sensors[j].respond(self.episode, scan, plan)
        if m is None:
            return
        self.counts.measured += 1
        self.sent_for[scan] += 1
        a = self.up[j].on_send(at)
        if a is None:
            self.counts.lost += 1
        else:
            heapq.heappush(self.pending, (a, next(self.seq), scan, j, m))

    def exchange(self, plan: Plan) -> tuple[list[Any], dict[str, Any]]:
        """Scan ``plan.k``: the command down every link at ``t_k``, the sensors' answers up
        theirs; at ``d_k``, the late messages (earlier scans) and scan ``k``'s on time."""
        k, counts = plan.k, self.counts
        t_k = k * self.T
        self.plans[k] = plan
        counts.commanded += len(plan.subset)
        for j, link in enumerate(self.down):  # Command(k) goes out on every downlink at t_k
            a = link.on_send(t_k)
            if a is not None:
                heapq.heappush(self.commands, (a, next(self.seq), j, k))
        d_k = t_k + self.delta * self.T
        # a missed command's fallback; with targets always off (no target, no window)
        fallback = "off" if self.engine.many else self.lat.missed_command
        # the sensors act on the commands that reach them by d_k, in time order
        while self.commands and self.commands[0][0] <= d_k:
            a, _, j, scan = heapq.heappop(self.commands)
            rx = self.receivers[j]
            if scan <= rx.newest:
                continue  # overtaken by a newer command: stale
            for m in range(rx.newest + 1, scan):  # commands it never got: its fallback
                counts.commands_missed += 1
                if self.measures_on_missed(fallback, rx.last_on):
                    counts.fallback_sent += 1
                    self._send(j, m, a, None)
            on = j in self.plans[scan].subset
            rx.newest, rx.last_on = scan, on
            if on:
                self._send(j, scan, a, self.plans[scan])
        on_time: dict[int, Any] = {}
        late: list[Any] = []
        while self.pending and self.pending[0][0] <= d_k:
            _, _, scan, j, m = heapq.heappop(self.pending)
            if scan == k:
                on_time[j] = m
            else:
                late.append(m)
        counts.on_time += len(on_time)
        # the fallbacks of earlier scans are late; one of this scan (a command overtaken by
        # the next) can be on time: covnet up's network.json counts those, so this does too
        counts.unsolicited += sum(j not in plan.subset for j in on_time)
        self.on_time_for[k] = len(on_time)
        counts.per_scan_fused.append(len(on_time))
        ids = self.engine.ids
        return late, {ids[j]: on_time[j] for j in sorted(on_time)}

    def late(self, refiltered: bool) -> None:
        """What became of a late message."""
        if refiltered:
            self.counts.late_refiltered += 1
        else:
            self.counts.late_dropped += 1

    def finish(self) -> LatencyCounts:
        """The counts, once the episode is over (what is still in flight never arrived)."""
        self.counts.lost += len(self.pending)
        self.counts.deadline_misses = int(np.sum(self.sent_for > self.on_time_for))
        return self.counts


def transport_for(engine: ScanEngine, episode: int, links: bool = False) -> Transport:
    """:class:`Direct`, or the slow links of ``network.latency`` (``links``: simulated even
    when they are ideal, for their counts)."""
    if not (engine.slow or links):
        return Direct(engine, episode)
    return SlowLinks(engine, episode)


def run_engine(engine: ScanEngine, links: bool = False) -> list[LatencyCounts | None]:
    """Every episode of ``engine`` in this process (module docstring); each episode's link
    counts (``links``: simulate the links even when ideal)."""
    counts: list[LatencyCounts | None] = []
    for e in range(len(engine.episodes)):
        engine.start_episode(e)
        transport = transport_for(engine, e, links)
        for k in range(1, engine.scans + 1):
            plan = engine.decide(k)
            late, arrived = transport.exchange(plan)
            for m in late:
                transport.late(engine.usable(m) and engine.insert_late(m))
            got = {sid: m for sid, m in arrived.items() if engine.usable(m)}
            engine.record(plan, engine.fuse(plan, got), got)
        counts.append(transport.finish())
    return counts


@dataclass(frozen=True)
class InProcessRun:
    """One metric's in-process run: its arrays (a :class:`~covnet.covariance_control.simulate.
    MetricRun`, or with targets a :class:`~covnet.covariance_control.simulate.TargetsRun`) and,
    over slow links, what the links did."""

    run: Any
    counts: LatencyCounts | None
    nodes: dict[str, Any] | None = None  # peer mode: every node's run (sensor id -> run)


def run(
    sc: Scenario, metric: str, model: Any = None, *, links: bool = False, many: bool | None = None
) -> InProcessRun:
    """``sc`` with allocation metric ``metric`` in this process (``model``: the config's
    model, or with targets its targets model, when the caller has it; ``links``: simulate
    ``network.latency``'s links even when they are ideal, for their counts; ``many``: through
    the many-target steps, also a config without ``targets:``)."""
    engine = ScanEngine(sc, [metric], model=model, many=many)
    counts = run_engine(engine, links)[0]
    nodes = engine.node_runs() if engine.peer else None
    return InProcessRun(engine.run_of(metric), counts, nodes)
