"""``covnet run``'s driver: THE in-process scan loop of the covariance-control kind.

It steps the kind's one scan logic (:class:`~covnet.covariance_control.engine.ScanEngine`)
with the sensors' answers handed over in this process, per scan ``k``::

    plan        = engine.decide(k)
    late, got   = transport.exchange(plan)     the enabled sensors' messages of scan k (and,
                                               over slow links, late ones of earlier scans)
    for m in late: transport.late(engine.insert_late(m))
    engine.report(plan, engine.fuse(plan, got), got)

The transport is :class:`Direct` (every enabled sensor's message arrives at once) or, when
``network.latency`` is not ideal, :class:`~covnet.covariance_control.links.SlowLinks` (the same
protocol in simulated time).  The manager process steps the same engine over zenoh
(:mod:`manager.covariance`), the replay with the recording's messages
(:mod:`covnet.covariance_control.replay`): one logic, three drivers.  Peer mode has no fusion
centre; its nodes' loop is :func:`covnet.covariance_control.decentral_sim.run_peer`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from covnet.covariance_control.config import Scenario
from covnet.covariance_control.engine import Plan, ScanEngine, SensorSide

if TYPE_CHECKING:
    from covnet.covariance_control.links import LatencyCounts

__all__ = ["Direct", "InProcessRun", "Transport", "run", "run_engine"]


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


def transport_for(engine: ScanEngine, episode: int, links: bool = False) -> Transport:
    """:class:`Direct`, or the slow links of ``network.latency`` (``links``: simulated even
    when they are ideal, for their counts)."""
    if not (engine.slow or links):
        return Direct(engine, episode)
    from covnet.covariance_control.links import SlowLinks  # start-up: slow links only

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
            late, got = transport.exchange(plan)
            for m in late:
                transport.late(engine.insert_late(m))
            engine.report(plan, engine.fuse(plan, got), got)
        counts.append(transport.finish())
    return counts


@dataclass(frozen=True)
class InProcessRun:
    """One metric's in-process run: its arrays (a :class:`~covnet.covariance_control.simulate.
    MetricRun`, or with targets a :class:`~covnet.covariance_control.simulate.TargetsRun`) and,
    over slow links, what the links did."""

    run: Any
    counts: LatencyCounts | None


def run(
    sc: Scenario, metric: str, model: Any = None, *, links: bool = False, many: bool | None = None
) -> InProcessRun:
    """``sc`` with allocation metric ``metric`` in this process (``model``: the config's
    model, or with targets its targets model, when the caller has it; ``links``: simulate
    ``network.latency``'s links even when they are ideal, for their counts; ``many``: through
    the many-target steps, also a config without ``targets:``)."""
    engine = ScanEngine(sc, [metric], model=model, many=many)
    counts = run_engine(engine, links)[0]
    return InProcessRun(engine.run_of(metric), counts)
