"""What Foxglove draws of a mobile run (:mod:`covnet.runs.visual`), in metres.

Per scan: each target's truth and track (state ``[px, vx, py, vy]``; the covariance's x-y block
``P[[0, 2]][:, [0, 2]]`` as 1σ and 2σ ellipses; a mobile scenario has no desired covariance),
every sensor at its platform's position of the scan (the Truth's ``platforms``; before the
first, its ``start_m``) with its detection scale ``r_pd_m`` as a circle, in its state (on: it
was commanded to measure a target this scan, off: alive with nothing to measure, failed), and a
line from each sensor to each target it was commanded to measure.  The numbers: ``N_k`` (the
sensors commanded to measure), ``f`` (the decision's objective), ``tr P`` (all tracks); per
target ``tr P``, the position error and the NEES against the truth.

:func:`run_messages` rebuilds an in-process run directory (``arrays.npz``) as messages, for
``covnet run --mcap``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from covnet.core.consistency import nees
from covnet.core.mobile.models import MODE_NAMES
from covnet.mobile.config import MobileConfig
from covnet.runs.rundir import ARRAYS, load_arrays
from covnet.runs.visual import XY, Coverage, Estimate, ScanMessages, SensorView, View, sensor_states
from covnet.wire import messages as msg

__all__ = ["Visual", "run_messages"]


class Visual:
    """The mobile kind's :class:`covnet.runs.visual.KindVisual`."""

    def __init__(self, cfg: MobileConfig) -> None:
        self.cfg = cfg
        self.ids = cfg.sensor_ids
        self.positions = {s.id: (float(s.start_m[0]), float(s.start_m[1])) for s in cfg.sensors}
        starts = np.array([s.start_m for s in cfg.sensors], dtype=float)
        self.marker = max(float(np.ptp(starts, axis=0).max()) / 100.0, 1.0)

    def view(self, scan: ScanMessages) -> View:
        st = scan.status
        tr = scan.truth
        truth: dict[str, np.ndarray] = {}
        if tr is not None:
            truth = {tid: tr.states[i] for i, tid in enumerate(tr.target_ids)}
            if tr.sensor_ids is not None and tr.platforms is not None:
                for j, sid in enumerate(tr.sensor_ids):
                    self.positions[sid] = (float(tr.platforms[j, 0]), float(tr.platforms[j, 1]))
        view = View(frame="world_m", marker=self.marker)
        view.truths = [(tid, (float(x[0]), float(x[2]), 0.0)) for tid, x in truth.items()]
        for t in scan.tracks:
            tid = t.target_id or "?"
            xt = truth.get(tid)
            view.estimates.append(
                Estimate(
                    id=tid,
                    position=(float(t.x[0]), float(t.x[2]), 0.0),
                    cov_xy=t.P[np.ix_(XY, XY)],
                    trace_P=float(np.trace(t.P)),
                    error=None if xt is None else float(np.hypot(*(t.x[XY] - xt[XY]))),
                    nees=None if xt is None else float(nees(xt, t.x, t.P)),
                )
            )
        tasks = (scan.command.targets if scan.command is not None else None) or {}
        states = sensor_states(st, self.ids)
        for s in self.cfg.sensors:
            measures = tuple(tasks.get(s.id, ()))
            state = states[s.id]
            if state == "on" and not measures:
                state = "off"  # alive, nothing to measure this scan
            x, y = self.positions[s.id]
            view.sensors.append(SensorView(s.id, (x, y, 0.0), state, Coverage(s.r_pd_m), measures))
        view.n_active = sum(1 for s in view.sensors if s.state == "on")
        view.f, view.trace_P = st.value, st.trace_P
        return view


def run_messages(cfg: MobileConfig, run_dir: Path) -> Iterator[msg.Message]:
    """The scans of an in-process mobile run directory (``arrays.npz``) as the manager and the
    world would have sent them: per scan a Command (modes, targets), the Truth (targets and
    platforms), a Track per target and the Status."""
    a = load_arrays(run_dir / ARRAYS)
    ids = tuple(str(s) for s in a["sensor_ids"])
    tids = tuple(str(s) for s in a["target_ids"])
    T = float(cfg.scan_period_s)
    for i in range(a["modes"].shape[0]):
        k, t = i + 1, (i + 1) * T
        assign = a["assign"][i]
        tasks = {
            sid: tuple(tids[n] for n in np.flatnonzero(assign == j)) for j, sid in enumerate(ids)
        }
        modes = {sid: MODE_NAMES[int(a["modes"][i, j])] for j, sid in enumerate(ids)}
        yield msg.Command(scan=k, t=t, enabled=ids, t_sent_ns=0, modes=modes, targets=tasks)
        pos, prev = a["platforms"][k], a["platforms"][k - 1]
        platforms = np.hstack([pos, (pos - prev) / T])
        yield msg.Truth(
            scan=k, t=t, target_ids=tids, states=a["truth"][k], sensor_ids=ids, platforms=platforms
        )
        x, P = a["x_est"][k], a["P_post"][k]
        for n, tid in enumerate(tids):
            yield msg.Track(scan=k, t=t, x=x[n], P=P[n], t_sent_ns=0, target_id=tid)
        objective = float(a["objective"][i])
        yield msg.Status(
            scan=k, t=t, enabled=ids, trace_P=float(np.trace(P, axis1=1, axis2=2).sum()),
            trace_Pd=0.0, value=objective if np.isfinite(objective) else 0.0, t_sent_ns=0,
            fused=ids,
        )  # fmt: skip
