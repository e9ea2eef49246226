"""The passive manager: the passive kind's maths in the scan skeleton (:mod:`manager.loop`).

What it plugs in, per scan ``k`` (lockstep; with ``--realtime`` one scan per second of scenario
time)::

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
    report   Track(k) per associated triple (x: position km, P: its covariance km²,
             ``target_id`` "i1-i2-i3"), Status(k) saying which lists were in (``fused``)

The manager draws each scan's scene itself for scoring only (which measurement came from which
target); it never sends it.  Each scan's association time is a wall-clock fact: it goes to
``run.json``, not to ``association.json``.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from covnet import messages as msg
from covnet.core.passive.model import PassiveScan
from covnet.passive.associate import header, scan_record
from covnet.passive.config import PassiveConfig, normalised
from covnet.passive.scene import draw
from covnet.rundir import CONFIG, RUN_INFO, write_json
from covnet.runtime_stats import NetStats
from manager import loop
from manager.loop import WORLD_ID, Decision, Loop, ScanReport
from manager.process import main_around, network_run_info

__all__ = ["MAX_LIST", "PassiveLogic", "PassiveResult", "main", "run", "write_network_run"]

MAX_LIST = 256
"""Longest list the manager associates (the candidate triples grow as n1·n2·n3)."""
SCAN_PERIOD_S = 1.0  # scenario time of scan k is k s (the scenes are static)


@dataclass
class PassiveResult:
    """What the loop has done so far (live while it runs; final when :func:`run` returns).

    ``scans``: one record per scan done: ``scan``, ``trial`` (= scan - 1), ``associated``,
    ``lists_from`` (the sensors whose lists arrived), ``missing``; when associated, the fields
    of :func:`covnet.passive.associate.scan_record`."""

    method: str
    seed: int
    scans: list[dict[str, Any]] = field(default_factory=list)
    failures: list[dict[str, Any]] = field(default_factory=list)
    stats: NetStats = field(default_factory=NetStats)
    completed: bool = False
    error: str | None = None
    association_time_s: list[float | None] = field(default_factory=list)  # per scan (run.json)

    @property
    def scans_done(self) -> int:
        return len(self.scans)

    @property
    def unassociated(self) -> int:
        return sum(not r["associated"] for r in self.scans)


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


class PassiveLogic:
    """The passive manager's steps (module docstring) for :func:`manager.loop.run_scans`."""

    message_type = msg.Measurement
    accept_unsolicited = False
    period_s = SCAN_PERIOD_S

    def __init__(self, cfg: PassiveConfig, loop: Loop) -> None:
        self.cfg, self.ids, self.clock = cfg, loop.ids, loop.clock
        self.method = cfg.association.method
        self.episodes = [self.method]
        self.scans = cfg.scans
        self.model = cfg.scene_model()
        self.params = cfg.assoc_params(self.model)
        self.result = PassiveResult(self.method, cfg.seed, stats=loop.stats)

    def start_episode(self, e: int) -> None:
        pass

    def membership(self, e: int, k: int, events: list[dict[str, Any]]) -> None:
        self.result.failures.extend(events)

    def decide(self, e: int, k: int, failed: frozenset[str]) -> Decision:
        return Decision(tuple(sid for sid in self.ids if sid not in failed))

    def ahead(self, e: int, k: int) -> None:
        pass

    def usable(self, m: msg.Measurement) -> bool:
        return usable_list(m)

    def on_late(self, m: Any) -> bool | None:
        return None

    def fuse(self, e: int, k: int, got: dict[str, msg.Measurement]) -> dict[str, Any]:
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

    def report(self, e: int, k: int, fused: dict[str, Any], failed: frozenset[str]) -> ScanReport:
        row, now, t = fused["row"], self.clock.now_ns, k * SCAN_PERIOD_S
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
                        t_sent_ns=now(),
                        target_id="-".join(str(n) for n in triple),
                    )
                )
                trace_P += float(np.trace(cov[i]))
            value = float(row["cost"]) if row["cost"] is not None else 0.0
        status = msg.Status(
            scan=k,
            t=t,
            enabled=tuple(sid for sid in self.ids if sid not in failed),
            trace_P=trace_P,
            trace_Pd=0.0,
            value=value,
            t_sent_ns=now(),
            fused=tuple(row["lists_from"]),
            failed=tuple(sorted(failed - {WORLD_ID})),
        )
        self.result.scans.append(row)
        self.result.association_time_s.append(fused["time_s"])
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


def association_doc(cfg: PassiveConfig, result: PassiveResult) -> dict[str, Any]:
    """``association.json`` of a network run: the run's fields, then the fields of the last
    associated scan at the top level (the shape ``covnet run`` writes for its one scan, which
    the scene figure reads), then ``scans``: every scan's record, and ``summary``."""
    done = [r for r in result.scans if r["associated"]]
    doc: dict[str, Any] = {"kind": "passive-network", **header(cfg, result.seed, result.method)}
    if done:
        doc |= {k: v for k, v in done[-1].items() if k not in ("associated", "missing")}
    scored = [r["score"] for r in done if "score" in r]
    doc["scans"] = result.scans
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
    write_json(out / "association.json", association_doc(cfg, result))
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


def main(args: Any, cfg: PassiveConfig, stop: threading.Event) -> int:
    """``python -m manager --config PASSIVE.yaml ...``: the process around :func:`run`."""
    return main_around(args, cfg, stop, run, write_network_run, write_every_s=2.0)
