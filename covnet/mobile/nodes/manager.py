"""The mobile manager: predict every track, decide modes and targets, command, collect, update.

Per scan ``k`` (the steps of :func:`covnet.mobile.simulate.run`, with the same functions)::

    1. predict every track to k                                  predict_tracks
    2. the sensors alive (liveliness + heartbeats, manager.membership); a failed sensor leaves
       the problem: decide(..., alive=mask) gives its targets to others or leaves them
       unobserved, and its platform stays
    3. Command(k): enabled = the alive sensors, modes and targets of each
    4. (compare_exact) the exact solver and the relaxation, while the sensors measure
    5. collect Measurement(k) from every enabled sensor until all arrived, one failed, or the
       deadline passed; anything malformed, for another scan, from a sensor not enabled,
       detecting a target it was not commanded or without its platform state is counted by
       reason and dropped
    6. each observed target updates with its detection (update_track, R from the sensor's
       reported position and velocity); publish Track(k) per target and Status(k)

The platforms' positions for the next decision are the ones the sensors reported; a sensor
that did not report is dead-reckoned from its commanded mode (move_platforms, as the world
moves it).  The truth is computed here for the results only (errors, the true Pd of each
chosen pair) and never sent.  The loop takes its bus, clock and stop event from the caller: a
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
from covnet.core.mobile.decision import compare, decide_milp, relaxation
from covnet.core.mobile.models import MODE_NAMES, predict_tracks, usage_cost
from covnet.mobile.config import MobileConfig
from covnet.mobile.model import (
    MobileModel,
    build_model,
    decide,
    initial_tracks,
    lp_reference,
    move_platforms,
    true_pd,
    truth,
    update_track,
)
from covnet.mobile.simulate import MobileRun
from covnet.runtime_stats import NetStats
from manager.node import WORLD_ID, ManagerError, _Loop, _pace, _speed

__all__ = ["MobileResult", "run"]


@dataclass
class MobileResult:
    """What the loop has done so far (live while it runs; final when :func:`run` returns)."""

    solver: str
    seed: int
    rows: dict[str, list[Any]] = field(default_factory=dict)
    failures: list[dict[str, Any]] = field(default_factory=list)
    stats: NetStats = field(default_factory=NetStats)
    completed: bool = False
    error: str | None = None
    x0: np.ndarray | None = None
    P0: np.ndarray | None = None
    pos0: np.ndarray | None = None
    truth: np.ndarray | None = None

    @property
    def scans_done(self) -> int:
        return len(self.rows.get("modes", ()))

    def as_run(self) -> MobileRun:
        """The scans done as a :class:`MobileRun` (``covnet run``'s arrays)."""
        assert self.x0 is not None and self.P0 is not None and self.pos0 is not None
        assert self.truth is not None
        n = self.scans_done
        r = self.rows

        def arr(name: str, dtype: Any = np.float64) -> np.ndarray:
            return np.array(r[name], dtype=dtype)

        def with_start(name: str, start: np.ndarray) -> np.ndarray:
            return np.array([start, *r[name]], dtype=np.float64)

        return MobileRun(
            solver=self.solver,
            seed=self.seed,
            truth=self.truth[: n + 1],
            x_est=with_start("x_est", self.x0),
            P_post=with_start("P_post", self.P0),
            platforms=with_start("platforms", self.pos0),
            modes=arr("modes", np.int64).reshape(n, len(self.pos0)),
            assign=arr("assign", np.int64).reshape(n, len(self.x0)),
            detected=arr("detected", bool).reshape(n, len(self.x0)),
            pd_true=arr("pd_true").reshape(n, len(self.x0)),
            usage=arr("usage"),
            objective=arr("objective"),
            status=arr("status", np.int64),
            fractional=arr("fractional", bool),
            J_lp=arr("J_lp"),
            J_post=arr("J_post"),
            J_star=arr("J_star"),
            J_relax=arr("J_relax"),
            gap=arr("gap"),
            conflicts=arr("conflicts", np.int64),
            mip_gap=arr("mip_gap"),
            exact_status=arr("exact_status", np.int64),
            cost_s=arr("cost_s"),
            solve_s=arr("solve_s"),
            compare_s=arr("compare_s"),
        )


_COMPARISON = "J_lp J_post J_star J_relax gap conflicts mip_gap exact_status compare_s".split()
_ROWS = (
    "x_est P_post platforms modes assign detected pd_true usage objective status fractional "
    "J_lp J_post J_star J_relax gap conflicts mip_gap exact_status cost_s solve_s compare_s"
).split()

StatusFn = Callable[[dict[str, Any]], None]


class _MobileLoop(_Loop):
    """The covariance-control manager's membership and bus helpers over a mobile model."""

    def __init__(self, cfg: MobileConfig, bus: Bus, run_id: str, clock: Clock) -> None:
        self.mobile: MobileModel = build_model(cfg)
        super().__init__(cfg.network, self.mobile.sensor_ids, bus, run_id, clock)

    def collect_mobile(
        self,
        k: int,
        waiting: set[str],
        commanded: dict[str, tuple[str, ...]],
        deadline: float,
        stop: threading.Event,
    ) -> dict[str, msg.Measurement]:
        """The shared collection (:meth:`_Loop.collect`); a mobile measurement must carry its
        platform state and detections of commanded targets only."""

        def usable(m: msg.Measurement) -> bool:
            return (
                m.platform is not None
                and m.target_ids is not None
                and m.z.shape[1] == 2
                and set(m.target_ids) <= set(commanded.get(m.sensor_id, ()))
            )

        return self.collect(0, k, waiting, deadline, stop, usable)


def run(
    cfg: MobileConfig,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    *,
    solver: str | None = None,
    realtime: bool = False,
    on_ready: Callable[[], None] | None = None,
    on_status: StatusFn | None = None,
    on_progress: Callable[[MobileResult, bool], None] | None = None,
) -> MobileResult:
    """Run the scans over the bus; returns what was done (also when stopped, with
    ``completed=False``, or when the network never came up, with ``error`` set)."""
    loop = _MobileLoop(cfg, bus, run_id, clock)
    model, ids = loop.mobile, loop.ids
    solver = solver or model.solver
    K, M = model.scans, model.M
    tids = model.target_ids
    net = cfg.network
    X = truth(model)  # for the results only; never sent by the manager
    x, P = initial_tracks(model)
    pos = model.sensors.position.copy()
    b = usage_cost(model.sensors.b0, model.sensors.b1)
    result = MobileResult(solver, model.seed, {n: [] for n in _ROWS}, stats=loop.stats)
    result.x0, result.P0, result.pos0, result.truth = x.copy(), P.copy(), pos.copy(), X
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
        for r in range(K):
            k = r + 1
            if stop.is_set():
                return result
            if realtime:
                _pace(clock, t_origin + r * model.T, stop)
            t_core0 = time.perf_counter_ns()
            xp, Pp = predict_tracks(x, P, model.targets)
            failed, events = loop.membership_changes(k, failed_prev)
            result.failures.extend(events)
            failed_prev = failed
            alive = np.array([sid not in failed for sid in ids])
            if not alive.any():
                raise ManagerError(f"scan {k}: every sensor has failed")
            step = decide(model, xp, Pp, pos, alive=alive, solver=solver)
            d = step.decision
            enabled = tuple(sid for sid, a in zip(ids, alive, strict=True) if a)
            targets = {
                sid: tuple(tids[i] for i in np.flatnonzero(d.assign == j))
                for j, sid in enumerate(ids)
                if alive[j]
            }
            core_ns = time.perf_counter_ns() - t_core0
            t_sent = clock.now_ns()
            cmd = msg.Command(
                scan=k,
                t=k * model.T,
                enabled=enabled,
                t_sent_ns=t_sent,
                modes={sid: MODE_NAMES[int(d.modes[j])] for j, sid in enumerate(ids) if alive[j]},
                targets=targets,
            )
            loop.publish_command(cmd)
            # while the sensors measure: the comparison with the exact solver (as covnet run)
            row: dict[str, Any] = {n: np.nan for n in ("J_lp", "J_post", "J_star", "J_relax")}
            row.update(gap=np.nan, mip_gap=np.nan, conflicts=-1, exact_status=-1, compare_s=0.0)
            row["J_lp"] = d.J_lp
            if d.solver != "milp":
                row["conflicts"], row["J_post"] = d.conflicts, d.objective
            if model.compare_exact:
                t0 = time.perf_counter()
                ref = lp_reference(step.problem, step)
                exact = d if d.solver == "milp" else decide_milp(step.problem, model.options)
                _, _, jr = relaxation(step.problem, model.options.linking)
                row["compare_s"] = time.perf_counter() - t0
                c = compare(ref, exact, jr)
                row.update(J_lp=c.J_lp, J_post=c.J_post, J_star=c.J_star, J_relax=jr)
                row.update(gap=c.gap, conflicts=c.conflicts, mip_gap=c.mip_gap)
                row["exact_status"] = c.exact_status
            if realtime:
                deadline = time.monotonic() + net.deadline_fraction * model.T / _speed(clock)
            else:
                deadline = time.monotonic() + net.scan_timeout_s
            got = loop.collect_mobile(k, set(enabled), targets, deadline, stop)
            t_core1 = time.perf_counter_ns()
            # platforms: as reported; a silent one dead-reckoned from its commanded mode
            pos_dr, qdot = move_platforms(model, pos, d.modes)
            pos = pos_dr.copy()
            for sid, m in got.items():
                j = ids.index(sid)
                assert m.platform is not None
                pos[j], qdot[j] = m.platform[:2], m.platform[2:]
            xn, Pn = xp.copy(), Pp.copy()
            detected = np.zeros(M, dtype=bool)
            pd = np.full(M, np.nan)
            usage = 0.0
            for i in np.flatnonzero(d.assign >= 0):
                j = int(d.assign[i])
                usage += b[j, d.modes[j]]
                pd[i] = true_pd(model, j, X[k, i], pos[j])
                m = got.get(ids[j])
                if m is not None and m.target_ids is not None and tids[i] in m.target_ids:
                    z = np.array(m.z[m.target_ids.index(tids[i])])
                    post = update_track(model, xp[i], Pp[i], z, j, pos[j], qdot[j])
                    xn[i], Pn[i] = post.x, post.P
                    detected[i] = True
            x, P = xn, Pn
            loop.stats.core_ns.append(core_ns + time.perf_counter_ns() - t_core1)
            loop.stats.scans_done += 1
            loop.stats.loop_wall_ns = time.perf_counter_ns() - t_loop
            latency_ms = (clock.now_ns() - t_sent) / 1e6
            loop.stats.scan_latency_ns.append(clock.now_ns() - t_sent)
            for i, tid in enumerate(tids):
                tr = msg.Track(
                    scan=k, t=k * model.T, x=x[i], P=P[i], t_sent_ns=clock.now_ns(), target_id=tid
                )
                loop.publish(loop.keys["track"], tr)
            trace_P = float(np.trace(P, axis1=1, axis2=2).sum())
            fused = tuple(sid for sid in ids if sid in got)
            failed_ids = tuple(sorted(failed - {WORLD_ID}))
            loop.publish(
                loop.keys["status"],
                msg.Status(
                    scan=k,
                    t=k * model.T,
                    enabled=enabled,
                    trace_P=trace_P,
                    trace_Pd=0.0,
                    value=float(d.objective) if np.isfinite(d.objective) else 0.0,
                    t_sent_ns=clock.now_ns(),
                    fused=fused,
                    failed=failed_ids,
                ),
            )
            rows = result.rows
            for name, value in (
                ("x_est", x),
                ("P_post", P),
                ("platforms", pos.copy()),
                ("modes", d.modes),
                ("assign", d.assign),
                ("detected", detected),
                ("pd_true", pd),
                ("usage", usage),
                ("objective", d.objective),
                ("status", d.status),
                ("fractional", d.fractional),
                ("cost_s", step.cost_s),
                ("solve_s", step.solve_s),
            ):
                rows[name].append(value)
            for name in _COMPARISON:
                rows[name].append(row[name])
            if on_status is not None:
                assigned_to = [ids[a] if a >= 0 else None for a in d.assign]
                assign = " ".join(
                    f"{tid}:{ids[a] if a >= 0 else '-'}{'+' if detected[i] else ''}"
                    for i, (tid, a) in enumerate(zip(tids, d.assign, strict=True))
                )
                info = f"scan {k}/{K}  {assign}  tr P {trace_P:.1f}  {latency_ms:.2f} ms"
                if failed_ids:
                    info += f"  failed {','.join(failed_ids)}"
                on_status(
                    {
                        "metric": solver,
                        "episode": 0,
                        "scan": k,
                        "scans": K,
                        "enabled": list(enabled),
                        "fused": list(fused),
                        "failed": list(failed_ids),
                        "assign": dict(zip(tids, assigned_to, strict=True)),
                        "trace_P": trace_P,
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
# the run directory and the process's main (called by ``python -m manager`` for kind: mobile)
# --------------------------------------------------------------------------------------------


def write_network_run(
    out: Any, cfg: MobileConfig, result: MobileResult, run_info: dict[str, Any] | None = None
) -> dict[str, Any] | None:
    """``covnet run``'s files for the scans done (summary.json, arrays.npz, config.json) plus
    ``network.json`` and the network's ``run.json``; None before the first scan."""
    from pathlib import Path

    from covnet.mobile.results import RUN_INFO, write_run
    from covnet.results import write_json

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "network.json", result.stats.as_dict())
    info: dict[str, Any] = {
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "mode": "network",
        "kind": "mobile",
        "solver": result.solver,
        "completed": result.completed,
        "scans_completed": result.scans_done,
        "failures": [{k: v for k, v in ev.items() if k != "detected_ns"} for ev in result.failures],
        "failure_detected_ns": [ev for ev in result.failures if "detected_ns" in ev],
        **(run_info or {}),
    }
    if result.error:
        info["error"] = result.error
    summary = write_run(out, cfg, result.as_run()) if result.scans_done else None
    write_json(out / RUN_INFO, info)
    return summary


def main_body(args: Any, cfg: MobileConfig, stop: threading.Event) -> int:
    """``python -m manager --config MOBILE.yaml ...``: the process around :func:`run`."""
    from pathlib import Path

    from covnet.core.mobile.decision import SOLVERS
    from manager.process import router_endpoint, serve
    from manager.process import run_info as base_run_info

    if args.metric:
        raise ValueError("--metric: a mobile scenario has no allocation metric; see --solver")
    solver = args.solver or cfg.solver
    if solver not in SOLVERS:
        raise ValueError(f"--solver: unknown solver {solver!r}; choose from {sorted(SOLVERS)}")
    endpoint = router_endpoint(cfg.network, args.listen)
    out = Path(args.out)
    run_info = base_run_info(args, endpoint)

    def run_loop(bus: Bus, clock: Clock, hooks: Any) -> MobileResult:
        return run(
            cfg,
            bus,
            args.run,
            clock,
            stop,
            solver=solver,
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
