"""The passive manager: the passive kind's maths in the scan skeleton (:mod:`manager.loop`).

The maths of each step (decide, usable, fuse, report) is
:class:`covnet.passive.network.PassiveSteps`, which ``covnet replay`` steps too; this module plugs
it into the skeleton and says what the live view shows (lockstep; with ``--realtime`` one scan
per second of scenario time).
"""

from __future__ import annotations

import threading
from functools import partial
from typing import Any

from covnet.passive.config import PassiveConfig
from covnet.passive.network import (
    MAX_LIST,
    SCAN_PERIOD_S,
    PassiveResult,
    PassiveSteps,
    association_doc,
    write_network_run,
)
from covnet.wire import messages as msg
from manager import loop
from manager.loop import Decision, Loop, ScanReport
from manager.process import main_around

__all__ = [
    "MAX_LIST",
    "PassiveLogic",
    "PassiveResult",
    "association_doc",
    "main",
    "run",
    "write_network_run",
]


class PassiveLogic:
    """The passive manager's steps (:class:`~covnet.passive.network.PassiveSteps`) for
    :func:`manager.loop.run_scans`."""

    message_type = msg.Measurement
    accept_unsolicited = False
    period_s = SCAN_PERIOD_S

    def __init__(self, cfg: PassiveConfig, loop: Loop) -> None:
        self.steps = PassiveSteps(cfg, loop.stats)
        self.clock = loop.clock
        self.method = self.steps.method
        self.episodes = [self.method]
        self.scans = cfg.scans
        self.result = self.steps.result

    def start_episode(self, e: int) -> None:
        pass

    def membership(self, e: int, k: int, events: list[dict[str, Any]]) -> None:
        self.result.failures.extend(events)

    def decide(self, e: int, k: int, failed: frozenset[str]) -> Decision:
        return Decision(self.steps.decide(failed).enabled)

    def ahead(self, e: int, k: int) -> None:
        pass

    def usable(self, m: msg.Measurement) -> bool:
        return self.steps.usable(m)

    def on_late(self, m: Any) -> bool | None:
        return None

    def fuse(self, e: int, k: int, got: dict[str, msg.Measurement]) -> dict[str, Any]:
        return self.steps.fuse(k, got)

    def report(self, e: int, k: int, fused: dict[str, Any], failed: frozenset[str]) -> ScanReport:
        row = fused["row"]
        tracks, status = self.steps.report(k, fused, failed, self.clock.now_ns)
        if row["missing"]:
            what = f"not associated (no list from {','.join(row['missing'])})"
        else:
            score = row.get("score", {})
            what = f"{len(tracks)} triples"
            if score:
                what += f", {score['correct']}/{score['truth']} correct"
        return ScanReport(
            tracks,
            status,
            {
                "associated": row["associated"],
                "triples": len(tracks),
                "info": f"scan {k}/{self.scans}  {self.method}: {what}",
                "info_short": f"{k}/{self.scans} {len(tracks)} triples",
            },
        )


run = partial(loop.run, PassiveLogic)
"""``run(cfg, bus, run_id, clock, stop, *, realtime, on_ready, on_status, on_progress)``: the
scans over the bus (:func:`manager.loop.run`); returns the :class:`PassiveResult`."""


def main(args: Any, cfg: PassiveConfig, stop: threading.Event) -> int:
    """``python -m manager --config PASSIVE.yaml ...``: the process around :func:`run`."""
    return main_around(args, cfg, stop, run, write_network_run, write_every_s=2.0)
