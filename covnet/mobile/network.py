"""The mobile manager's maths per scan, with no bus, and its run directory: the manager process
(:mod:`manager.mobile`, over the scan skeleton) and ``covnet replay`` / the rebuild after a
manager crash (:mod:`covnet.mobile.replay`, over a recording) both step :class:`MobileSteps`
and write with :func:`write_network_run`, so a replay recomputes exactly what the manager did.

Per scan ``k`` (the steps of :func:`covnet.mobile.simulate.run`, with the same functions)::

    decide   predict every track to k (predict_tracks); a failed sensor leaves the problem
             (decide(..., alive=mask) gives its targets to others or leaves them unobserved,
             and its platform stays); Command(k): enabled = the alive sensors, the mode and
             the targets of each
    ahead    (compare_exact) the exact solver and the relaxation, while the sensors measure
    usable   a measurement must carry its platform state and one detection (a row of z) of
             each commanded target it names, and no other; the platform state must be the one
             its commanded mode gives (move_platforms from the platform's last state, as the
             world moves it: the position is known exactly, spec §3.2), else ``bad_platform``;
             each detection must pass the validation gate under its target's prediction
             (passes_gate: χ², a tail of 1e-9), else ``outside_gate``: counted, never fused
    fuse     each observed target updates with its detection (update_track, R from the
             platform's position and velocity after this scan's move); the platforms for the
             next decision are those (move_platforms of the commanded modes; a failed sensor
             stays)
    report   the scan's rows into the result; Track(k) per target and Status(k) with
             tr P = Σ_i tr P_i and value = the decision's objective (0 when not finite)

The truth is computed here for the results only (errors, the true Pd of each chosen pair) and
never sent.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from covnet.core.mobile.decision import compare, decide_milp, relaxation
from covnet.core.mobile.models import MODE_NAMES, predict_tracks, usage_cost
from covnet.mobile.config import MobileConfig
from covnet.mobile.model import (
    build_model,
    decide,
    initial_tracks,
    lp_reference,
    move_platforms,
    passes_gate,
    true_pd,
    truth,
    update_track,
)
from covnet.mobile.results import write_run
from covnet.mobile.simulate import MobileRun
from covnet.processes.network_run import ScanDecision, ScanImpossible, network_run_info
from covnet.processes.runtime_stats import NetStats
from covnet.runs.columns import Column
from covnet.runs.rundir import RUN_INFO, write_json
from covnet.wire import messages as msg

__all__ = ["MobileResult", "MobileSteps", "write_network_run"]


@dataclass
class MobileResult:
    """What the scans have given so far (live while the manager runs; final at its end)."""

    solver: str
    seed: int
    rows: ScanRows = field(default_factory=lambda: ScanRows())
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
        return self.rows.count("modes")

    def as_run(self) -> MobileRun:
        """The scans done as a :class:`MobileRun` (``covnet run``'s arrays)."""
        assert self.x0 is not None and self.P0 is not None and self.pos0 is not None
        assert self.truth is not None
        n = self.scans_done
        r = self.rows

        def arr(name: str, dtype: Any = np.float64) -> np.ndarray:
            assert r.dtype(name) == np.dtype(dtype), name
            return r.array(name)

        def with_start(name: str, start: np.ndarray) -> np.ndarray:
            rows = r.array(name) if n else np.empty((0, *np.shape(start)))
            return np.concatenate([np.asarray(start, dtype=np.float64)[None], rows])

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
_DTYPES = {
    **dict.fromkeys(("modes", "assign", "status", "conflicts", "exact_status"), np.int64),
    **dict.fromkeys(("detected", "fractional"), np.bool_),
}
"""Each row's dtype in ``covnet run``'s arrays (float64 where not named)."""


class ScanRows:
    """The manager's per-scan rows by name, each a :class:`~covnet.runs.columns.Column` of the
    dtype ``covnet run``'s arrays give it (made at its first row, of that row's shape): a long
    run's rows go to the columns' spill files as blocks fill (as Python lists of arrays they
    grew the manager by about 2 kB a scan).  ``array(name)`` is ``np.array(rows, dtype)``, bit
    for bit (a None of a float row is NaN, as there)."""

    def __init__(self) -> None:
        self._cols: dict[str, Column] = {}

    def append(self, name: str, value: Any) -> None:
        col = self._cols.get(name)
        dtype = self.dtype(name) if col is None else col.dtype
        if dtype.kind == "f":
            value = np.asarray(value, dtype=np.float64)  # (None -> NaN, as np.array does)
        if col is None:
            col = self._cols[name] = Column(np.shape(value), dtype)
        col.append(value)

    def count(self, name: str) -> int:
        col = self._cols.get(name)
        return 0 if col is None else len(col)

    def dtype(self, name: str) -> np.dtype[Any]:
        return np.dtype(_DTYPES.get(name, np.float64))

    def array(self, name: str) -> np.ndarray:
        col = self._cols.get(name)
        return np.empty((0,), dtype=self.dtype(name)) if col is None else col.array()


class MobileSteps:
    """The mobile manager's steps (module docstring), one scan at a time: :meth:`decide`,
    :meth:`ahead`, then :meth:`fuse` of what arrived (each message passing :meth:`usable`) and
    :meth:`report`, which logs the scan into :attr:`result`."""

    def __init__(self, cfg: MobileConfig, stats: NetStats | None = None) -> None:
        self.model = model = build_model(cfg)
        self.ids, self.tids = model.sensor_ids, model.target_ids
        self.solver = model.solver
        self.X = truth(model)  # for the results only; never sent by the manager
        self.x, self.P = initial_tracks(model)
        self.pos = model.sensors.position.copy()
        self.b = usage_cost(model.sensors.b0, model.sensors.b1)
        self.commanded: dict[str, tuple[str, ...]] = {}
        self.result = MobileResult(self.solver, model.seed, ScanRows(), stats=stats or NetStats())
        r = self.result
        r.x0, r.P0, r.pos0, r.truth = self.x.copy(), self.P.copy(), self.pos.copy(), self.X

    def decide(self, failed: frozenset[str]) -> ScanDecision:
        """Predict every track and decide over the sensors not in ``failed``: enabled = the
        alive sensors, with the mode and the targets of each; :class:`~covnet.processes.network_run.
        ScanImpossible` when none is alive."""
        model, ids, tids = self.model, self.ids, self.tids
        alive = np.array([sid not in failed for sid in ids])
        if not alive.any():
            raise ScanImpossible("every sensor has failed")
        self.xp, self.Pp = predict_tracks(self.x, self.P, model.targets)
        self.step = step = decide(
            model, self.xp, self.Pp, self.pos, alive=alive, solver=self.solver
        )
        d = step.decision
        self.moved = move_platforms(model, self.pos, d.modes)
        self.commanded = {
            sid: tuple(tids[i] for i in np.flatnonzero(d.assign == j))
            for j, sid in enumerate(ids)
            if alive[j]
        }
        return ScanDecision(
            enabled=tuple(sid for sid, a in zip(ids, alive, strict=True) if a),
            modes={sid: MODE_NAMES[int(d.modes[j])] for j, sid in enumerate(ids) if alive[j]},
            targets=self.commanded,
        )

    def ahead(self) -> None:
        """The comparison with the exact solver (as ``covnet run`` makes it)."""
        step, d = self.step, self.step.decision
        row: dict[str, Any] = {n: np.nan for n in ("J_lp", "J_post", "J_star", "J_relax")}
        row.update(gap=np.nan, mip_gap=np.nan, conflicts=-1, exact_status=-1, compare_s=0.0)
        row["J_lp"] = d.J_lp
        if d.solver != "milp":
            row["conflicts"], row["J_post"] = d.conflicts, d.objective
        else:  # HiGHS's own gap, with or without the comparison (as covnet run records it)
            row["mip_gap"] = d.mip_gap
        if self.model.compare_exact:
            t0 = time.perf_counter()
            ref = lp_reference(step.problem, step)
            exact = d if d.solver == "milp" else decide_milp(step.problem, self.model.options)
            _, _, jr = relaxation(step.problem, self.model.options.linking)
            row["compare_s"] = time.perf_counter() - t0
            c = compare(ref, exact, jr)
            row.update(J_lp=c.J_lp, J_post=c.J_post, J_star=c.J_star, J_relax=jr)
            row.update(gap=c.gap, conflicts=c.conflicts, mip_gap=c.mip_gap)
            row["exact_status"] = c.exact_status
        self.row = row

    def usable(self, m: msg.Measurement) -> bool | str:
        """The module docstring's test: True, False (``bad_measurement``: no platform state,
        detections that are not ``(n, 2)`` rows of this scan's commanded targets, one each),
        ``bad_platform`` or ``outside_gate``."""
        mine = self.commanded.get(m.sensor_id, ())
        if (
            m.platform is None
            or m.target_ids is None
            or m.z.shape != (len(m.target_ids), 2)
            or len(set(m.target_ids)) != len(m.target_ids)
            or not set(m.target_ids) <= set(mine)
        ):
            return False
        j = self.ids.index(m.sensor_id)
        pos, qdot = self.moved
        # the world's move of the same state by the same mode: the same bits; a margin for
        # nothing but a reordering of the arithmetic
        if not np.allclose(m.platform, np.hstack([pos[j], qdot[j]]), rtol=1e-9, atol=1e-6):
            return "bad_platform"
        for z, tid in zip(m.z, m.target_ids, strict=True):
            i = self.tids.index(tid)
            if not passes_gate(self.model, self.xp[i], self.Pp[i], z, j, pos[j], qdot[j]):
                return "outside_gate"
        return True

    def fuse(self, k: int, got: dict[str, msg.Measurement]) -> dict[str, Any]:
        """Scan ``k``'s rows from the usable measurements ``got`` (sensor id -> message)."""
        model, ids, tids, d = self.model, self.ids, self.tids, self.step.decision
        # platforms: moved by their commanded modes (a usable report says the same)
        pos, qdot = self.moved
        xn, Pn = self.xp.copy(), self.Pp.copy()
        detected = np.zeros(model.M, dtype=bool)
        pd = np.full(model.M, np.nan)
        usage = 0.0
        for i in np.flatnonzero(d.assign >= 0):
            j = int(d.assign[i])
            usage += self.b[j, d.modes[j]]
            pd[i] = true_pd(model, j, self.X[k, i], pos[j])
            meas = got.get(ids[j])
            if meas is not None and meas.target_ids is not None and tids[i] in meas.target_ids:
                z = np.array(meas.z[meas.target_ids.index(tids[i])])
                post = update_track(model, self.xp[i], self.Pp[i], z, j, pos[j], qdot[j])
                xn[i], Pn[i] = post.x, post.P
                detected[i] = True
        self.x, self.P, self.pos = xn, Pn, pos
        return {
            "x_est": xn,
            "P_post": Pn,
            "platforms": pos.copy(),
            "modes": d.modes,
            "assign": d.assign,
            "detected": detected,
            "pd_true": pd,
            "usage": usage,
            "objective": d.objective,
            "status": d.status,
            "fractional": d.fractional,
            "cost_s": self.step.cost_s,
            "solve_s": self.step.solve_s,
            **{name: self.row[name] for name in _COMPARISON},
            "_enabled": tuple(sid for sid in ids if sid in self.commanded),
            "_fused": tuple(sid for sid in ids if sid in got),
        }

    def report(
        self, k: int, fused: dict[str, Any], failed: frozenset[str], now_ns: Callable[[], int]
    ) -> tuple[list[msg.Track], msg.Status]:
        """Log scan ``k`` into :attr:`result`; its Track per target and its Status (stamped
        with ``now_ns()``; ``failed`` without the world)."""
        t = k * self.model.T
        x, P = fused["x_est"], fused["P_post"]
        tracks = [
            msg.Track(scan=k, t=t, x=x[i], P=P[i], t_sent_ns=now_ns(), target_id=tid)
            for i, tid in enumerate(self.tids)
        ]
        objective = float(fused["objective"])
        status = msg.Status(
            scan=k,
            t=t,
            enabled=fused["_enabled"],
            trace_P=float(np.trace(P, axis1=1, axis2=2).sum()),
            trace_Pd=0.0,
            value=objective if np.isfinite(objective) else 0.0,
            t_sent_ns=now_ns(),
            fused=fused["_fused"],
            failed=tuple(sorted(failed - {msg.WORLD_ID})),
        )
        for name in _ROWS:
            self.result.rows.append(name, fused[name])
        return tracks, status


def write_network_run(
    out: Path, cfg: MobileConfig, result: MobileResult, run_info: dict[str, Any] | None = None
) -> dict[str, Any] | None:
    """``covnet run``'s files for the scans done (summary.json, arrays.npz, config.json) plus
    ``network.json`` and the network's ``run.json``; None before the first scan."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "network.json", result.stats.as_dict())
    info = network_run_info("mobile", result, result.scans_done, run_info, solver=result.solver)
    if not result.scans_done:
        write_json(out / RUN_INFO, info)
        return None
    return write_run(out, cfg, result.as_run(), run_info=info)
