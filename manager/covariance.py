"""The covariance-control manager: the kind's one scan engine in the scan skeleton.

One *episode* per allocation metric (the paper compares three on the same scenario).  The
steps it plugs into :func:`manager.loop.run_scans` are those of
:class:`covnet.covariance_control.engine.ScanEngine` (decide, ahead, usable, late, fuse,
report), which ``covnet run`` steps in process and ``covnet replay`` with the recording's
messages: this module only turns the engine's plans and outcomes into the bus's Command,
Track and Status, so a lockstep network run reproduces the in-process run bit for bit.  One
target or many, any fusion rule at a centre, ideal or slow links: entries the engine consults.
In peer mode (``fusion.mode: peer``) there is no fusion centre: this process only routes and
watches (:mod:`manager.peer_monitor`).
"""

from __future__ import annotations

import threading
from functools import partial
from typing import Any

from covnet.covariance_control.config import Scenario
from covnet.covariance_control.engine import Outcome, Plan, ScanEngine
from covnet.covariance_control.peer_run import write_peer_run
from covnet.covariance_control.results import write_network_run
from covnet.wire import messages as msg
from manager import loop, peer_monitor
from manager.loop import WORLD_ID, Decision, Loop, ManagerError, ScanReport
from manager.process import main_around

__all__ = ["CovarianceLogic", "main", "run"]


class CovarianceLogic:
    """:class:`~covnet.covariance_control.engine.ScanEngine` as the skeleton's
    :class:`~manager.loop.ScanLogic`: messages in, messages out."""

    def __init__(self, sc: Scenario, loop: Loop) -> None:
        if not sc.fusion.has_centre:
            raise ManagerError("peer mode has no fusion manager: run manager.peer_monitor")
        self.engine = ScanEngine(sc, stats=loop.stats)
        self.ids = self.engine.ids
        self.episodes = self.engine.episodes
        self.scans, self.period_s = self.engine.scans, self.engine.period_s
        self.message_type: type[msg.Measurement] | type[msg.LocalTrack] = (
            msg.LocalTrack if self.engine.tracks else msg.Measurement
        )
        self.accept_unsolicited = self.engine.accept_unsolicited
        self.slow = self.engine.slow
        self.clock = loop.clock
        self.result = self.engine.result

    def start_episode(self, e: int) -> None:
        self.engine.start_episode(e)

    def membership(self, e: int, k: int, events: list[dict[str, Any]]) -> None:
        self.engine.failures(events)

    def decide(self, e: int, k: int, failed: frozenset[str]) -> Decision:
        self.plan = self.engine.decide(k, self.engine.unavailable(failed))
        return Decision(self.plan.enabled, targets=self.plan.targets, windows=self.plan.windows)

    def ahead(self, e: int, k: int) -> None:
        self.engine.ahead(self.plan)

    def usable(self, m: Any) -> bool | str:
        verdict = self.engine.verdict(m)
        return True if verdict is None else verdict

    def usable_many(self, ms: list[Any]) -> list[bool | str]:
        """:meth:`usable` of each message (the engine's verdicts computed together)."""
        return [True if v is None else v for v in self.engine.verdicts(ms)]

    def on_late(self, m: Any) -> bool | None:
        return self.engine.insert_late(m) if self.slow else None

    def fuse(self, e: int, k: int, got: dict[str, Any]) -> tuple[Plan, Any, dict[str, Any]]:
        return self.plan, self.engine.fuse(self.plan, got), got

    def report(
        self, e: int, k: int, fused: tuple[Plan, Any, dict[str, Any]], failed: frozenset[str]
    ) -> ScanReport:
        plan, done, got = fused
        out = self.engine.report(plan, done, got)
        tracks, status = messages_of(out, e, self.period_s, failed, self.clock.now_ns)
        return ScanReport(tracks, status, out.lines(self.scans, len(self.ids)))


def messages_of(
    out: Outcome, e: int, period_s: float, failed: frozenset[str], now_ns: Any
) -> tuple[list[msg.Track], msg.Status]:
    """The Track(s) and Status of a scan's outcome (``now_ns``: their send time)."""
    k, t = out.k, out.k * period_s
    states = out.track_states or (None,) * len(out.tracks)  # surveillance: the tracks' states
    tracks = [
        msg.Track(
            scan=k, t=t, x=g.x, P=g.P, t_sent_ns=now_ns(), episode=e, target_id=tid, state=st
        )
        for (tid, g), st in zip(out.tracks, states, strict=True)
    ]
    status = msg.Status(
        scan=k,
        t=t,
        enabled=out.enabled,
        trace_P=out.trace_P,
        trace_Pd=out.trace_Pd,
        value=out.value,
        t_sent_ns=now_ns(),
        episode=e,
        fused=out.fused,
        failed=tuple(sorted(failed - {WORLD_ID})),
        refiltered=out.refiltered,
        cells=out.cells,
    )
    return tracks, status


run = partial(loop.run, CovarianceLogic)
"""``run(sc, bus, run_id, clock, stop, *, realtime, on_ready, on_status, on_progress)``: every
metric's episode (``allocation.metrics``) over the bus (:func:`manager.loop.run`); returns the
:class:`~covnet.covariance_control.centre.ManagerResult`."""


def main(args: Any, sc: Scenario, stop: threading.Event) -> int:
    """``python -m manager --config PAPER.yaml ...``: the process around :func:`run` (or, in
    peer mode, around the observer :func:`manager.peer_monitor.run`)."""
    info = {"episodes": list(sc.allocation.metrics)}
    if not sc.fusion.has_centre:  # no fusion centre: this process only routes and watches
        if args.realtime:
            raise ValueError("--realtime: peer mode runs in lockstep only")
        return main_around(args, sc, stop, peer_monitor.run, write_peer_run, run_info_extra=info)
    return main_around(args, sc, stop, run, write_network_run, run_info_extra=info)
