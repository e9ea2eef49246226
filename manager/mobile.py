"""The mobile manager: the mobile kind's maths in the scan skeleton (:mod:`manager.loop`).

The maths of each step (decide, ahead, usable, fuse, report) is
:class:`covnet.mobile.network.MobileSteps`, which ``covnet replay`` steps too; this module plugs
it into the skeleton and says what the live view shows.  The truth is computed for the results
only (errors, the true Pd of each chosen pair) and never sent.
"""

from __future__ import annotations

import threading
from functools import partial
from typing import Any

import numpy as np

from covnet.mobile.config import MobileConfig
from covnet.mobile.network import MobileResult, MobileSteps, write_network_run
from covnet.processes.network_run import ScanImpossible
from covnet.wire import messages as msg
from manager import loop
from manager.loop import Decision, Loop, ManagerError, ScanReport
from manager.process import main_around

__all__ = ["MobileLogic", "MobileResult", "main", "run", "write_network_run"]


class MobileLogic:
    """The mobile manager's steps (:class:`~covnet.mobile.network.MobileSteps`) for
    :func:`manager.loop.run_scans`."""

    message_type = msg.Measurement
    accept_unsolicited = False

    def __init__(self, cfg: MobileConfig, loop: Loop) -> None:
        self.steps = MobileSteps(cfg, loop.stats)
        self.ids, self.tids = loop.ids, self.steps.tids
        self.clock = loop.clock
        self.episodes = [self.steps.solver]
        self.scans, self.period_s = self.steps.model.scans, self.steps.model.T
        self.result = self.steps.result

    def start_episode(self, e: int) -> None:
        pass

    def membership(self, e: int, k: int, events: list[dict[str, Any]]) -> None:
        self.result.failures.extend(events)

    def decide(self, e: int, k: int, failed: frozenset[str]) -> Decision:
        try:
            d = self.steps.decide(failed)
        except ScanImpossible as exc:
            raise ManagerError(f"scan {k}: {exc}") from None
        return Decision(enabled=d.enabled, modes=d.modes, targets=d.targets)

    def ahead(self, e: int, k: int) -> None:
        self.steps.ahead()

    def usable(self, m: msg.Measurement) -> bool | str:
        return self.steps.usable(m)

    def on_late(self, m: Any) -> bool | None:
        return None

    def fuse(self, e: int, k: int, got: dict[str, msg.Measurement]) -> dict[str, Any]:
        return self.steps.fuse(k, got)

    def report(self, e: int, k: int, fused: dict[str, Any], failed: frozenset[str]) -> ScanReport:
        ids, tids = self.ids, self.tids
        tracks, status = self.steps.report(k, fused, failed, self.clock.now_ns)
        trace_P = status.trace_P
        detected, assign = fused["detected"], fused["assign"]
        pairs = " ".join(
            f"{tid}:{ids[a] if a >= 0 else '-'}{'+' if detected[i] else ''}"
            for i, (tid, a) in enumerate(zip(tids, assign, strict=True))
        )
        return ScanReport(
            tracks,
            status,
            {
                "assign": {
                    tid: ids[a] if a >= 0 else None for tid, a in zip(tids, assign, strict=True)
                },
                "trace_P": trace_P,
                "info": f"scan {k}/{self.scans}  {pairs}  tr P {trace_P:.1f}",
                "info_short": (
                    f"{k}/{self.scans} {int(np.count_nonzero(assign >= 0))}/{len(tids)} "
                    f"assigned, {int(detected.sum())} detected  trP {trace_P:.0f}"
                ),
            },
        )


run = partial(loop.run, MobileLogic)
"""``run(cfg, bus, run_id, clock, stop, *, realtime, on_ready, on_status, on_progress)``: the
scans over the bus (:func:`manager.loop.run`); returns the :class:`MobileResult`."""


def main(args: Any, cfg: MobileConfig, stop: threading.Event) -> int:
    """``python -m manager --config MOBILE.yaml ...``: the process around :func:`run`."""
    return main_around(args, cfg, stop, run, write_network_run, write_every_s=2.0)
