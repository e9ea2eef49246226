"""What Foxglove draws of a covariance-control run (:mod:`covnet.runs.visual`), in metres.

Per scan: each target's truth and fused estimate (state ``[x, vx, y, vy]``: the position is
``(x, y)``, the covariance's x-y block ``P[[0, 2]][:, [0, 2]]``), its 1σ and 2σ ellipses and the
desired covariance's x-y block as an ellipse around the estimate; every sensor in its state
(on: enabled this scan, off, failed: seen failed by the manager), its coverage (``max_range_m``,
``fov``) where it has one, and a line from each enabled sensor to the target it measures (the
one target of a paper config; with ``targets:``, the command's dwell).  The numbers: ``N_k``
(the enabled sensors), ``f`` (the manager's allocation value), ``tr P`` and ``tr P_d`` (the
Status's), per target ``f(P, P_d)`` of the episode's metric on the fused posterior, ``tr P``,
``tr P_d``, the position error and the NEES against the truth.  Surveillance: the manager's
tracks (``K<id>``) by state (tentative, confirmed, deleted at the scan) and the search cells
shaded by their undetected mass ``u_c`` (the Status's ``cells``).

A paper sensor has no position (it measures the target's position directly): such sensors are
drawn in a row under the first estimate, labelled "(no position)", so that the lines to the
target show who measured.

:func:`run_messages` rebuilds an in-process run directory's scans (``arrays.npz``) as the
messages the network would have sent, for ``covnet run --mcap``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from covnet.core.consistency import nees
from covnet.core.metrics import METRICS
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.model import build_model
from covnet.errors import UsageError
from covnet.runs.rundir import ARRAYS, load_arrays
from covnet.runs.visual import (
    XY,
    Area,
    Coverage,
    Estimate,
    ScanMessages,
    SensorView,
    View,
    sensor_states,
)
from covnet.wire import messages as msg

__all__ = ["Visual", "mcap_problem", "run_messages"]


class Visual:
    """The covariance-control kind's :class:`covnet.runs.visual.KindVisual`."""

    def __init__(self, sc: Scenario) -> None:
        self.sc = sc
        self.ids = sc.sensor_ids
        self.episodes = list(sc.allocation.metrics)
        if sc.surveillance is not None:
            # the tracks are the manager's (K<id>), each drawn against its state's P_d
            des = sc.surveillance.desired
            self._by_state = {
                state: np.diag(c.diag) if c.diag is not None else np.asarray(c.matrix, np.float64)
                for state, c in (("confirmed", des.confirmed), ("tentative", des.tentative))
            }
            self.target_ids: tuple[str, ...] = ()
            self._desired: dict[str, Any] = {}
            grid = sc.surveillance.grid()
            self.cells = np.zeros((0, 4)) if grid is None else grid.boxes()
        elif sc.multitarget:
            # start-up: the many-target model only for configs with targets
            from covnet.covariance_control import targets

            tm = targets.build(sc)
            self.target_ids = tuple(tm.target_ids)
            self._desired = {
                tid: tg.desired for tid, tg in zip(tm.target_ids, tm.targets, strict=True)
            }
        else:
            model = build_model(sc)
            self.target_ids = ("T1",)
            self._desired = {"T1": model.desired}
        placed = [s.position_m for s in sc.sensors if s.position_m is not None]
        if placed:
            span = float(np.ptp(np.asarray(placed), axis=0).max()) if len(placed) > 1 else 0.0
            self.marker = max(span / 150.0, 1.0)
        else:
            self.marker = 0.0  # set per scan from the desired covariance

    def desired(self, tid: str, k: int, state: str | None = None) -> np.ndarray:
        if tid not in self._desired:  # surveillance: a track of the manager's, by its state
            return np.asarray(self._by_state.get(state or "confirmed", self._by_state["confirmed"]))
        return np.asarray(self._desired[tid](k))

    def view(self, scan: ScanMessages) -> View:
        st, k = scan.status, scan.scan
        metric = (
            METRICS.get(self.episodes[scan.episode]) if scan.episode < len(self.episodes) else None
        )
        truth: dict[str, np.ndarray] = {}
        if scan.truth is not None:
            truth = {tid: scan.truth.states[i] for i, tid in enumerate(scan.truth.target_ids)}
        ids = self.target_ids or tuple(tr.target_id or "" for tr in scan.tracks) or ("",)
        sd = float(np.sqrt(max(self.desired(t, k)[0, 0] for t in ids)))
        view = View(frame="world_m", marker=self.marker or max(sd / 2.0, 0.5))
        view.truths = [(tid, (float(x[0]), float(x[2]), 0.0)) for tid, x in truth.items()]
        for tr in scan.tracks:
            tid = tr.target_id or self.target_ids[0]
            known = tid in self._desired or not self.target_ids
            Pd = self.desired(tid, k, tr.state) if known else None
            xt = truth.get(tid)
            view.estimates.append(
                Estimate(
                    id=tid,
                    position=(float(tr.x[0]), float(tr.x[2]), 0.0),
                    cov_xy=tr.P[np.ix_(XY, XY)],
                    desired_xy=None if Pd is None else Pd[np.ix_(XY, XY)],
                    f=None if metric is None or Pd is None else float(metric(tr.P, Pd)),
                    trace_P=float(np.trace(tr.P)),
                    trace_Pd=None if Pd is None else float(np.trace(Pd)),
                    error=None if xt is None else float(np.hypot(*(tr.x[XY] - xt[XY]))),
                    nees=None if xt is None else float(nees(xt, tr.x, tr.P)),
                    state=tr.state,
                )
            )
        u = st.cells
        if u is not None and self.sc.surveillance is not None and u.shape == (len(self.cells),):
            top = max(float(u.max()), 1e-12) if u.size else 1.0
            view.areas = [
                Area(
                    f"C{c}", float(x0), float(x1), float(y0), float(y1), float(uc), float(uc) / top
                )
                for c, ((x0, x1, y0, y1), uc) in enumerate(zip(self.cells, u, strict=True))
            ]
        states = sensor_states(st, self.ids)
        tasks = scan.command.targets if scan.command is not None else None
        anchor = view.estimates[0].position if view.estimates else (0.0, 0.0, 0.0)
        n_unplaced = sum(s.position_m is None for s in self.sc.sensors)
        i = 0
        for s in self.sc.sensors:
            if s.position_m is not None:
                pos = (float(s.position_m[0]), float(s.position_m[1]), 0.0)
            else:  # a row under the estimate
                pos = (anchor[0] + (i - (n_unplaced - 1) / 2) * 3 * sd, anchor[1] - 8 * sd, 0.0)
                i += 1
            cov = None
            if s.max_range_m is not None:
                fov = s.fov
                cov = Coverage(
                    s.max_range_m,
                    None if fov is None else fov.center_deg,
                    None if fov is None else fov.half_width_deg,
                )
            if tasks is not None:
                measures = tuple(tasks.get(s.id, ()))
            else:
                measures = self.target_ids if not self.sc.multitarget else ()
            view.sensors.append(
                SensorView(s.id, pos, states[s.id], cov, measures, placed=s.position_m is not None)
            )
        view.n_active = len(st.enabled)
        view.f, view.trace_P, view.trace_Pd = st.value, st.trace_P, st.trace_Pd
        return view


def mcap_problem(sc: Scenario) -> str | None:
    """Why ``covnet run --mcap`` cannot rebuild ``sc``'s scenes from its run directory (None:
    it can): a surveillance run's tracks come and go, which ``arrays.npz`` does not keep as
    messages."""
    if sc.surveillance is not None:
        return (
            "a surveillance run's scene is recorded by covnet up (covnet up CONFIG "
            "--foxglove); covnet run --mcap draws the known-target scenarios"
        )
    return None


def run_messages(sc: Scenario, run_dir: Path) -> Iterator[msg.Message]:
    """The scans of an in-process run directory (``arrays.npz``) as the manager and the world
    would have sent them: per episode and scan a Command, the Truth, the Track(s) and the
    Status (no Measurement: ``covnet run`` keeps no raw measurement)."""
    problem = mcap_problem(sc)
    if problem is not None:
        raise UsageError(f"--mcap: {problem}")
    a = load_arrays(run_dir / ARRAYS)
    ids = sc.sensor_ids
    ts = a["t"]
    for e, m in enumerate(sc.allocation.metrics):
        enabled_rows = a[f"enabled.{m}"]
        for i, t in enumerate(ts):
            k, t = i + 1, float(t)
            enabled = tuple(ids[j] for j in np.flatnonzero(enabled_rows[i]))
            if sc.multitarget:
                tids = tuple(str(x) for x in a["target_ids"])
                asg = a[f"assignment.{m}"][i]
                tasks: dict[str, tuple[str, ...]] = {
                    ids[j]: (tids[asg[j]],) for j in np.flatnonzero(asg >= 0)
                }
                yield msg.Command(
                    scan=k, t=t, enabled=enabled, t_sent_ns=0, episode=e, targets=tasks
                )
                yield msg.Truth(scan=k, t=t, target_ids=tids, states=a["truth"][:, i])
                xs, Ps = a[f"x_est.{m}"][:, i], a[f"P_post.{m}"][:, i]
                for j, tid in enumerate(tids):
                    yield msg.Track(
                        scan=k, t=t, x=xs[j], P=Ps[j], t_sent_ns=0, episode=e, target_id=tid
                    )
                trace_P = float(sum(np.trace(P) for P in Ps))
                trace_Pd = float(np.trace(a["P_d"][:, i], axis1=1, axis2=2).sum())
            else:
                yield msg.Command(scan=k, t=t, enabled=enabled, t_sent_ns=0, episode=e)
                yield msg.Truth(scan=k, t=t, target_ids=("T1",), states=a["truth"][i][None, :])
                P = a[f"P_post.{m}"][i]
                yield msg.Track(scan=k, t=t, x=a[f"x_est.{m}"][i], P=P, t_sent_ns=0, episode=e)
                trace_P, trace_Pd = float(np.trace(P)), float(np.trace(a["P_d"][i]))
            yield msg.Status(
                scan=k, t=t, enabled=enabled, trace_P=trace_P, trace_Pd=trace_Pd,
                value=float(a[f"value.{m}"][i]), t_sent_ns=0, episode=e, fused=enabled,
            )  # fmt: skip
