"""What Foxglove draws of a passive run (:mod:`covnet.runs.visual`), in kilometres, in 3-D.

Per scan: the true targets (the Truth's positions), the three sensors (on: their list was
asked for, failed: seen failed), every line of sight of the scan's three lists (from the
sensor along ``(cos ε cos α, cos ε sin α, sin ε)``, as far as the formation and a quarter
more), and each associated triple: the triangulated position with the 1σ and 2σ ellipses of
its covariance's x-y block and a line from each of the three sensors to it.  The numbers:
``N_k`` (the lists asked for), ``f`` (the association's cost), ``tr P`` (all triples); per
triple (id ``i1-i2-i3``, the measurement index in each list) ``tr P``, the distance to the
nearest true target and the NEES against it.  A passive run has no desired covariance.

:func:`run_messages` rebuilds an in-process run directory (``association.json``: its lists)
as messages, the triples from the manager's own steps (:class:`covnet.passive.network.
PassiveSteps`), for ``covnet run --mcap``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from covnet.core.consistency import nees
from covnet.core.passive.model import los_vectors
from covnet.passive.config import PassiveConfig
from covnet.runs.visual import Estimate, ScanMessages, Segment, SensorView, View, sensor_states
from covnet.wire import messages as msg

__all__ = ["Visual", "run_messages"]


class Visual:
    """The passive kind's :class:`covnet.runs.visual.KindVisual`."""

    measurements = True  # the lines of sight

    def __init__(self, cfg: PassiveConfig) -> None:
        self.cfg = cfg
        self.ids = cfg.sensor_ids
        self.positions = {s.id: tuple(float(v) for v in s.position_km) for s in cfg.sensors}
        t = cfg.targets
        centre = np.array([t.center_km[0], t.center_km[1], t.altitude_km])
        far = max(float(np.linalg.norm(centre - np.array(p))) for p in self.positions.values())
        self.los_km = 1.25 * far + 2.0 * t.spacing_km
        self.marker = max(t.spacing_km / 10.0, 0.01)

    def view(self, scan: ScanMessages) -> View:
        st = scan.status
        view = View(frame="world_km", marker=self.marker)
        truth = np.empty((0, 3))
        if scan.truth is not None:
            truth = scan.truth.states
            view.truths = [
                (tid, (float(x[0]), float(x[1]), float(x[2])))
                for tid, x in zip(scan.truth.target_ids, truth, strict=True)
            ]
        states = sensor_states(st, self.ids)
        for sid in self.ids:
            p = self.positions[sid]
            view.sensors.append(SensorView(sid, p, states[sid]))  # type: ignore[arg-type]
            m = scan.measurements.get(sid)
            if m is None or m.z.shape[1] != 2:
                continue
            u = los_vectors(m.z[:, 0], m.z[:, 1])
            for i, d in enumerate(u):
                end = tuple(float(v) for v in np.asarray(p) + self.los_km * d)
                view.segments.append(Segment(f"los/{sid}/{i}", p, end, "los"))  # type: ignore[arg-type]
        for t in scan.tracks:
            tid = t.target_id or "?"
            pos = (float(t.x[0]), float(t.x[1]), float(t.x[2]))
            error = nees_ = None
            if len(truth):
                d = np.linalg.norm(truth - t.x, axis=1)
                j = int(np.argmin(d))
                error, nees_ = float(d[j]), float(nees(truth[j], t.x, t.P))
            view.estimates.append(
                Estimate(
                    id=tid, position=pos, cov_xy=t.P[:2, :2], trace_P=float(np.trace(t.P)),
                    error=error, nees=nees_,
                )
            )  # fmt: skip
            for sid in self.ids:
                p = self.positions[sid]
                view.segments.append(Segment(f"triple/{tid}/{sid}", p, pos, "triple"))  # type: ignore[arg-type]
        view.n_active = len(st.enabled)
        view.f, view.trace_P = st.value, st.trace_P
        return view


def run_messages(cfg: PassiveConfig, run_dir: Path) -> Iterator[msg.Message]:
    """The scan of an in-process passive run directory (``association.json``: scan 1, its
    three lists) as the network would have sent it: the Command, the Truth, the three
    Measurements and, from the manager's own steps on those lists, the Tracks and the Status."""
    # start-up: the association's steps only for covnet run --mcap
    from covnet.passive.network import SCAN_PERIOD_S, PassiveSteps

    doc = json.loads((run_dir / "association.json").read_text())
    ids = cfg.sensor_ids
    k, t = 1, SCAN_PERIOD_S
    yield msg.Command(scan=k, t=t, enabled=ids, t_sent_ns=0)
    targets = np.asarray(doc["targets_km"], dtype=np.float64)
    yield msg.Truth(
        scan=k, t=t, target_ids=tuple(f"T{i + 1}" for i in range(len(targets))), states=targets
    )
    R = np.diag(
        [(1e-3 * cfg.noise.sigma_azimuth_mrad) ** 2, (1e-3 * cfg.noise.sigma_elevation_mrad) ** 2]
    )
    got = {}
    for sid, rows in zip(ids, doc["measurements"], strict=True):
        z = np.array([[r["azimuth_rad"], r["elevation_rad"]] for r in rows]).reshape(-1, 2)
        got[sid] = msg.Measurement(sensor_id=sid, scan=k, t=t, z=z, R=R, t_sent_ns=0, seq=1)
        yield got[sid]
    steps = PassiveSteps(cfg)
    steps.decide(frozenset())
    tracks, status = steps.report(k, steps.fuse(k, got), frozenset(), lambda: 0)
    yield from tracks
    yield status
