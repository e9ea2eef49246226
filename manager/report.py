"""The manager's part of the run directory: the same files as ``covnet run`` plus
``network.json`` (the bus's own record) and the failures seen."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from covnet.config import Scenario
from covnet.model import build_model
from covnet.results import write_json, write_run
from covnet.simulate import shared_trajectory
from manager.node import ManagerResult


def write_network_run(
    out: Path, sc: Scenario, result: ManagerResult, run_info: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Write summary/arrays/config (as ``covnet run`` does, for the scans done) and
    ``network.json``; safe to call repeatedly while the run goes on."""
    model = build_model(sc)
    traj = shared_trajectory(model)
    n_sensors = len(model.sensor_ids)
    runs = {m: log.as_run(n_sensors) for m, log in result.episodes.items() if log.value}
    extra: dict[str, Any] = {
        "completed": result.completed,
        "scans_completed": {m: len(log.value) for m, log in result.episodes.items()},
        "failures": {
            m: [{k: v for k, v in ev.items() if k != "detected_ns"} for ev in log.failures]
            for m, log in result.episodes.items()
        },
    }
    info: dict[str, Any] = {
        "mode": "network",
        "failure_detected_ns": {
            m: [ev for ev in log.failures if "detected_ns" in ev]
            for m, log in result.episodes.items()
        },
    }
    info.update(run_info or {})
    summary = write_run(out, sc, traj, runs, extra=extra, run_info=info)
    write_json(out / "network.json", result.stats.as_dict())
    return summary
