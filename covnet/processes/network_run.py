"""What the per-scan steps of the single-episode kinds (mobile, passive: ``covnet.<kind>.network``)
share, be they stepped by the manager process over the bus or by a replay over a recording
(``covnet replay``, the launcher after a manager crash): the decision they hand out and the
``run.json`` their network-run writers write.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from covnet import __version__
from covnet.code_identity import code_identity
from covnet.runs.rundir import utc_now

__all__ = ["ScanDecision", "ScanImpossible", "network_run_info"]


@dataclass(frozen=True)
class ScanDecision:
    """Scan ``k``'s command: the enabled sensors, and what some kinds add per sensor (motion
    ``modes``, ``targets`` to measure: see :class:`covnet.wire.messages.Command`)."""

    enabled: tuple[str, ...]
    modes: dict[str, str] | None = None
    targets: dict[str, tuple[str, ...]] | None = None


class ScanImpossible(ValueError):
    """The steps cannot decide the scan at all (e.g. every sensor has failed)."""


def network_run_info(
    kind: str, result: Any, scans_done: int, run_info: dict[str, Any] | None, **facts: Any
) -> dict[str, Any]:
    """``run.json`` of a network run whose ``result`` logs its failures in one list: the kind,
    whether it completed, the scans done, the failure and rejoin events (their detection times
    apart, being wall-clock), the error if any, the kind's ``facts`` and the process's
    ``run_info``."""
    info: dict[str, Any] = {
        "created_utc": utc_now(),
        "covnet_version": __version__,
        "code": code_identity(),  # covnet.code_identity: the source that ran the manager
        "mode": "network",
        "kind": kind,
        **facts,
        "completed": result.completed,
        "scans_completed": scans_done,
        "failures": [{k: v for k, v in ev.items() if k != "detected_ns"} for ev in result.failures],
        "failure_detected_ns": [ev for ev in result.failures if "detected_ns" in ev],
        **(run_info or {}),
    }
    if result.error:
        info["error"] = result.error
    return info
