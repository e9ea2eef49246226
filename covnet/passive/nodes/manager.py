"""The passive manager: command a scan, collect the three lists, associate, triangulate, publish.

Per scan ``k`` (lockstep; with ``--realtime`` one scan per second of scenario time)::

    1. the sensors alive (liveliness + heartbeats, manager.membership)
    2. Command(k): enabled = the alive sensors
    3. collect Measurement(k) from every enabled sensor until all arrived, one failed, or the
       deadline (``network.scan_timeout_s``) passed.  A list is accepted only when it is one
       (n, 2) array of angles (azimuth in [-π, π], elevation in (-π/2, π/2)), n <= MAX_LIST,
       R a 2x2 with a positive diagonal, and nothing else (no target_ids, no platform);
       anything else, or for another scan, from a sensor not enabled, or a second list, is
       counted by reason (``bad_measurement``, ``late``, ``wrong_scan``, ``duplicate``,
       ``not_enabled``, ``key_mismatch`` or a wire reason) and dropped
    4. all three lists in: associate them with the configured method
       (:func:`covnet.passive.associate.scan_record`, what ``covnet run`` calls) and triangulate;
       publish Track(k) per associated triple (x: position km, P: its covariance km²,
       ``target_id`` "i1-i2-i3") and Status(k).  A list missing (a sensor failed or silent):
       the scan is not associated (``unassociated`` in the results, with the missing sensors)
       and Status(k) says which lists were in (``fused``) and who failed

The manager draws each scan's scene itself for scoring only (which measurement came from which
target); it never sends it.  The loop takes its bus, clock and stop event from the caller: a
test runs it in a thread over ``InMemoryBus``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from covnet import messages as msg
from covnet.bus import Bus
from covnet.clock import Clock
from covnet.core.passive.model import PassiveScan
from covnet.passive.associate import header, scan_record
from covnet.passive.config import PassiveConfig
from covnet.passive.scene import draw
from covnet.runtime_stats import NetStats
from manager.node import WORLD_ID, ManagerError, _Loop, _pace

__all__ = ["MAX_LIST", "PassiveResult", "run", "write_network_run"]

MAX_LIST = 256
"""Longest list the manager associates (the candidate triples grow as n1·n2·n3)."""
SCAN_PERIOD_S = 1.0  # scenario time of scan k is k s (the scenes are static)

StatusFn = Callable[[dict[str, Any]], None]


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


class _PassiveLoop(_Loop):
    """The manager's membership and bus helpers over the three passive sensors."""

    def collect_lists(
        self, k: int, waiting: set[str], deadline: float, stop: threading.Event
    ) -> dict[str, msg.Measurement]:
        """The shared collection (:meth:`_Loop.collect`) with the passive list check."""
        return self.collect(0, k, waiting, deadline, stop, usable_list)


def run(
    cfg: PassiveConfig,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    *,
    realtime: bool = False,
    on_ready: Callable[[], None] | None = None,
    on_status: StatusFn | None = None,
    on_progress: Callable[[PassiveResult, bool], None] | None = None,
) -> PassiveResult:
    """Run the scans over the bus; returns what was done (also when stopped, with
    ``completed=False``, or when the network never came up, with ``error`` set)."""
    loop = _PassiveLoop(cfg.network, cfg.sensor_ids, bus, run_id, clock)
    ids = loop.ids
    method = cfg.association.method
    model = cfg.scene_model()
    params = cfg.assoc_params(model)
    K = cfg.scans
    result = PassiveResult(method, cfg.seed, stats=loop.stats)
    try:
        try:
            loop.wait_ready(stop)
        except ManagerError as exc:
            result.error = str(exc)
            return result
        if on_ready is not None:
            on_ready()
        t_loop = time.perf_counter_ns()
        t_origin = clock.now()
        failed_prev: frozenset[str] = frozenset()
        for k in range(1, K + 1):
            if stop.is_set():
                return result
            if realtime:
                _pace(clock, t_origin + (k - 1) * SCAN_PERIOD_S, stop)
            failed, events = loop.membership_changes(k, failed_prev)
            result.failures.extend(events)
            failed_prev = failed
            enabled = tuple(sid for sid in ids if sid not in failed)
            t_sent = clock.now_ns()
            cmd = msg.Command(scan=k, t=k * SCAN_PERIOD_S, enabled=enabled, t_sent_ns=t_sent)
            loop.publish_command(cmd)
            deadline = time.monotonic() + cfg.network.scan_timeout_s
            got = loop.collect_lists(k, set(enabled), deadline, stop)
            t_core0 = time.perf_counter_ns()
            lists_from = [sid for sid in ids if sid in got]
            missing = [sid for sid in ids if sid not in got]
            row: dict[str, Any] = {
                "scan": k,
                "trial": k - 1,
                "associated": not missing,
                "lists_from": lists_from,
                "missing": missing,
            }
            trace_P, value, n_tracks = 0.0, 0.0, 0
            if not missing:
                scan = PassiveScan(model.sensors, tuple(np.array(got[s].z) for s in ids))  # type: ignore[arg-type]
                truth = draw(model, cfg.seed, k - 1)  # for scoring only; never sent
                rec, pos, cov = scan_record(scan, params, method, truth, warm=k == 1)
                row |= rec
                for i, t in enumerate(rec["triples"]):
                    if not np.all(np.isfinite(cov[i])):
                        continue  # degenerate geometry: no covariance to publish
                    loop.publish(
                        loop.keys["track"],
                        msg.Track(
                            scan=k,
                            t=k * SCAN_PERIOD_S,
                            x=pos[i],
                            P=cov[i],
                            t_sent_ns=clock.now_ns(),
                            target_id="-".join(str(n) for n in t),
                        ),
                    )
                    trace_P += float(np.trace(cov[i]))
                    n_tracks += 1
                value = float(rec["cost"]) if rec["cost"] is not None else 0.0
            loop.stats.core_ns.append(time.perf_counter_ns() - t_core0)
            loop.stats.scans_done += 1
            loop.stats.loop_wall_ns = time.perf_counter_ns() - t_loop
            latency_ms = (clock.now_ns() - t_sent) / 1e6
            loop.stats.scan_latency_ns.append(clock.now_ns() - t_sent)
            failed_ids = tuple(sorted(failed - {WORLD_ID}))
            loop.publish(
                loop.keys["status"],
                msg.Status(
                    scan=k,
                    t=k * SCAN_PERIOD_S,
                    enabled=enabled,
                    trace_P=trace_P,
                    trace_Pd=0.0,
                    value=value,
                    t_sent_ns=clock.now_ns(),
                    fused=tuple(lists_from),
                    failed=failed_ids,
                ),
            )
            result.scans.append(row)
            if on_status is not None:
                if missing:
                    what = f"not associated (no list from {','.join(missing)})"
                else:
                    sc = row.get("score", {})
                    what = f"{n_tracks} triples"
                    if sc:
                        what += f", {sc['correct']}/{sc['truth']} correct"
                info = f"scan {k}/{K}  {method}: {what}  {latency_ms:.2f} ms"
                if failed_ids:
                    info += f"  failed {','.join(failed_ids)}"
                on_status(
                    {
                        "metric": method,
                        "episode": 0,
                        "scan": k,
                        "scans": K,
                        "enabled": list(enabled),
                        "fused": lists_from,
                        "failed": list(failed_ids),
                        "associated": not missing,
                        "triples": n_tracks,
                        "latency_ms": latency_ms,
                        "messages": loop.traffic()[0],
                        "bytes": loop.traffic()[1],
                        "info": info,
                    }
                )
            if on_progress is not None:
                on_progress(result, k == K)
        result.completed = True
    except ManagerError as exc:
        result.error = str(exc)
    finally:
        loop.token.undeclare()
    return result


# --------------------------------------------------------------------------------------------
# the run directory and the process's main (called by ``python -m manager`` for kind: passive)
# --------------------------------------------------------------------------------------------


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
    out: Any, cfg: PassiveConfig, result: PassiveResult, run_info: dict[str, Any] | None = None
) -> None:
    """``association.json``, ``config.json``, ``network.json`` and ``run.json``."""
    from pathlib import Path

    from covnet.passive.config import normalised
    from covnet.results import write_json

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "network.json", result.stats.as_dict())
    write_json(out / "config.json", normalised(cfg))
    write_json(out / "association.json", association_doc(cfg, result))
    info: dict[str, Any] = {
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "mode": "network",
        "kind": "passive",
        "method": result.method,
        "completed": result.completed,
        "scans_completed": result.scans_done,
        "scans_unassociated": result.unassociated,
        "failures": [{k: v for k, v in ev.items() if k != "detected_ns"} for ev in result.failures],
        "failure_detected_ns": [ev for ev in result.failures if "detected_ns" in ev],
        **(run_info or {}),
    }
    if result.error:
        info["error"] = result.error
    write_json(out / "run.json", info)


def main_body(args: Any, cfg: PassiveConfig, stop: threading.Event) -> int:
    """``python -m manager --config PASSIVE.yaml ...``: the process around :func:`run`."""
    from pathlib import Path

    from manager.process import router_endpoint, serve
    from manager.process import run_info as base_run_info

    if args.metric:
        raise ValueError("--metric: a passive scenario has no allocation metric")
    if args.solver:
        raise ValueError("--solver: a passive scenario names its method in association.method")
    endpoint = router_endpoint(cfg.network, args.listen)
    out = Path(args.out)
    run_info = base_run_info(args, endpoint)

    def run_loop(bus: Bus, clock: Clock, hooks: Any) -> PassiveResult:
        return run(
            cfg,
            bus,
            args.run,
            clock,
            stop,
            realtime=args.realtime,
            **hooks.kwargs(),
        )

    return serve(
        args,
        cfg.network,
        cfg.sensor_ids,
        stop,
        endpoint,
        run_loop,
        lambda result: write_network_run(out, cfg, result, run_info),
        write_every_s=2.0,
    )
