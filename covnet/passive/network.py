"""The passive manager's maths per scan, with no bus, and its run directory: the manager
process (:mod:`manager.passive`, over the scan skeleton) and ``covnet replay`` / the rebuild
after a manager crash (:mod:`covnet.passive.replay`, over a recording) both step
:class:`PassiveSteps` and write with :func:`write_network_run`, so a replay recomputes exactly
what the manager did.

Per scan ``k`` (lockstep; with ``--realtime`` one scan per second of scenario time)::

    decide   Command(k): enabled = the sensors alive
    usable   a list is accepted only when it is one (n, 2) array of angles (azimuth in
             [-π, π], elevation in (-π/2, π/2)), n <= MAX_LIST, R a 2x2 with a positive
             diagonal, and nothing else (no target_ids, no platform); anything else is counted
             (``bad_measurement``) and dropped, as are lists for another scan, from a sensor not
             enabled, or a second list (the skeleton's reasons)
    fuse     all three lists in: associate them with the configured method
             (:func:`covnet.passive.associate.scan_record`, what ``covnet run`` calls) and
             triangulate.  A list missing (a sensor failed or silent): the scan is not
             associated (``unassociated`` in the results, with the missing sensors)
    report   Track(k) per associated triple with a finite covariance (x: position km, P: its
             covariance km², ``target_id`` "i1-i2-i3"), Status(k) saying which lists were in
             (``fused``), tr P = Σ tr P over those tracks and value = the association's cost

The manager draws each scan's scene itself for scoring only (which measurement came from which
target); it never sends it.  Each scan's association time is a wall-clock fact: it goes to
``run.json``, not to ``association.json``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from covnet.core.passive.model import PassiveScan
from covnet.passive.associate import header, scan_record
from covnet.passive.config import PassiveConfig, normalised
from covnet.passive.scene import draw
from covnet.processes.network_run import ScanDecision, network_run_info
from covnet.processes.runtime_stats import NetStats
from covnet.runs.columns import Records
from covnet.runs.rundir import CONFIG, RUN_INFO, write_json
from covnet.wire import messages as msg

__all__ = [
    "ASSOCIATION",
    "MAX_LIST",
    "SCAN_PERIOD_S",
    "PassiveResult",
    "PassiveSteps",
    "association_doc",
    "usable_list",
    "write_network_run",
]

ASSOCIATION = "association.json"
MAX_LIST = 112
"""Longest list the manager associates (the candidate triples grow as n1·n2·n3): the longest
an honest sensor sends, its 5 targets and ``Poisson(λ)`` false returns at the largest
``clutter.rate_per_scan`` (:data:`~covnet.passive.config.MAX_PASSIVE_RATE`, 50), whose
``1e-12`` upper tail is 107. At 256 (the old bound) one list stalled the manager for 20 s and
4 GB (``cot``) or ran it out of memory (``lr``)."""
SCAN_PERIOD_S = 1.0  # scenario time of scan k is k s (the scenes are static)


@dataclass
class PassiveResult:
    """What the scans have given so far (live while the manager runs; final at its end).

    ``scans``: one record per scan done: ``scan``, ``trial`` (= scan - 1), ``associated``,
    ``lists_from`` (the sensors whose lists arrived), ``missing``; when associated, the fields
    of :func:`covnet.passive.associate.scan_record`."""

    method: str
    seed: int
    scans: Records = field(default_factory=Records)  # off the heap as they add up
    failures: list[dict[str, Any]] = field(default_factory=list)
    stats: NetStats = field(default_factory=NetStats)
    completed: bool = False
    error: str | None = None
    association_time_s: list[float | None] = field(default_factory=list)  # per scan (run.json)

    @property
    def scans_done(self) -> int:
        return len(self.scans)

    unassociated: int = 0


def usable_list(m: msg.Measurement) -> bool:
    """A passive sensor's list: ``(n, 2)`` angles in range, ``n <= MAX_LIST``, a 2x2 ``R`` with
    a positive diagonal, and none of the other kinds' optional fields."""
    z, R = m.z, m.R
    return (
        m.target_ids is None
        and m.platform is None
        and z.ndim == 2
        and z.shape[1] == 2
        and z.shape[0] <= MAX_LIST
        and R.shape == (2, 2)
        and bool(R[0, 0] > 0 and R[1, 1] > 0)
        and bool(np.all(np.abs(z[:, 0]) <= np.pi))
        and bool(np.all(np.abs(z[:, 1]) < np.pi / 2))
    )


class PassiveSteps:
    """The passive manager's steps (module docstring), one scan at a time: :meth:`decide`,
    then :meth:`fuse` of the lists that arrived (each passing :meth:`usable`:
    :func:`usable_list`) and :meth:`report`, which logs the scan into :attr:`result`."""

    def __init__(self, cfg: PassiveConfig, stats: NetStats | None = None) -> None:
        self.cfg, self.ids = cfg, cfg.sensor_ids
        self.method = cfg.association.method
        self.model = cfg.scene_model()
        self.params = cfg.assoc_params(self.model)
        self.result = PassiveResult(self.method, cfg.seed, stats=stats or NetStats())

    def decide(self, failed: frozenset[str]) -> ScanDecision:
        """The enabled set: every sensor not in ``failed``."""
        return ScanDecision(tuple(sid for sid in self.ids if sid not in failed))

    def ahead(self) -> None:
        """Nothing to do while the sensors measure."""

    def usable(self, m: msg.Measurement) -> bool:
        return usable_list(m)

    def fuse(self, k: int, got: dict[str, msg.Measurement]) -> dict[str, Any]:
        """Scan ``k``'s record from the lists ``got`` (sensor id -> message)."""
        ids = self.ids
        lists_from = [sid for sid in ids if sid in got]
        missing = [sid for sid in ids if sid not in got]
        row: dict[str, Any] = {
            "scan": k,
            "trial": k - 1,
            "associated": not missing,
            "lists_from": lists_from,
            "missing": missing,
        }
        positions: np.ndarray | None = None
        covariances: np.ndarray | None = None
        dt: float | None = None
        if not missing:
            z1, z2, z3 = (np.array(got[s].z) for s in ids)
            scan = PassiveScan(self.model.sensors, (z1, z2, z3))
            truth = draw(self.model, self.cfg.seed, k - 1)  # for scoring only; never sent
            rec, positions, covariances = scan_record(
                scan, self.params, self.method, truth, warm=k == 1
            )
            dt = rec.pop("time_s")
            row |= rec
        return {"row": row, "positions": positions, "covariances": covariances, "time_s": dt}

    def report(
        self, k: int, fused: dict[str, Any], failed: frozenset[str], now_ns: Callable[[], int]
    ) -> tuple[list[msg.Track], msg.Status]:
        """Log scan ``k`` into :attr:`result`; its Tracks and its Status (stamped with
        ``now_ns()``; ``failed`` without the world)."""
        row, t = fused["row"], k * SCAN_PERIOD_S
        tracks: list[msg.Track] = []
        trace_P, value = 0.0, 0.0
        if row["associated"]:
            pos, cov = fused["positions"], fused["covariances"]
            for i, triple in enumerate(row["triples"]):
                if not np.all(np.isfinite(cov[i])):
                    continue  # degenerate geometry: no covariance to publish
                tracks.append(
                    msg.Track(
                        scan=k,
                        t=t,
                        x=pos[i],
                        P=cov[i],
                        t_sent_ns=now_ns(),
                        target_id="-".join(str(n) for n in triple),
                    )
                )
                trace_P += float(np.trace(cov[i]))
            value = float(row["cost"]) if row["cost"] is not None else 0.0
        status = msg.Status(
            scan=k,
            t=t,
            enabled=self.decide(failed).enabled,
            trace_P=trace_P,
            trace_Pd=0.0,
            value=value,
            t_sent_ns=now_ns(),
            fused=tuple(row["lists_from"]),
            failed=tuple(sorted(failed - {msg.WORLD_ID})),
        )
        self.result.scans.append(row)
        self.result.unassociated += not row["associated"]
        self.result.association_time_s.append(fused["time_s"])
        return tracks, status


def association_doc(cfg: PassiveConfig, result: PassiveResult) -> dict[str, Any]:
    """``association.json`` of a network run: the run's fields, then the fields of the last
    associated scan at the top level (the shape ``covnet run`` writes for its one scan, which
    the scene figure reads), then ``scans``: every scan's record, and ``summary``."""
    scans = result.scans.list()
    done = [r for r in scans if r["associated"]]
    doc: dict[str, Any] = {"kind": "passive-network", **header(cfg, result.seed, result.method)}
    if done:
        doc |= {k: v for k, v in done[-1].items() if k not in ("associated", "missing")}
    scored = [r["score"] for r in done if "score" in r]
    doc["scans"] = scans
    doc["summary"] = {
        "scans": result.scans_done,
        "associated": len(done),
        "unassociated": result.unassociated,
        "correct": sum(s["correct"] for s in scored),
        "truth": sum(s["truth"] for s in scored),
        "output": sum(s["output"] for s in scored),
        "exact_scans": sum(bool(s["exact"]) for s in scored),
    }
    return doc


def write_network_run(
    out: Path, cfg: PassiveConfig, result: PassiveResult, run_info: dict[str, Any] | None = None
) -> None:
    """``association.json``, ``config.json``, ``network.json`` and ``run.json``."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "network.json", result.stats.as_dict())
    write_json(out / CONFIG, normalised(cfg))
    write_json(out / ASSOCIATION, association_doc(cfg, result))
    info = network_run_info(
        "passive",
        result,
        result.scans_done,
        run_info,
        method=result.method,
        scans_unassociated=result.unassociated,
        association_time_s=result.association_time_s,
    )
    write_json(out / RUN_INFO, info)
