"""One scan associated and triangulated, as a JSON-able record: what ``covnet run`` writes for its
single scan and what the network manager writes for each of its scans (the same function, so
the two agree bit for bit on the same lists).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from covnet.core.passive.methods import METHODS
from covnet.core.passive.model import AssocParams, PassiveScan
from covnet.core.passive.sd import _normal_eq, triangulate
from covnet.passive.config import PassiveConfig, config_hash
from covnet.passive.scene import Scene, score

__all__ = ["header", "json_number", "scan_record"]


def json_number(v: Any) -> Any:
    """Plain JSON: numpy scalars to Python, non-finite floats to None."""
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def header(cfg: PassiveConfig, seed: int, method: str) -> dict[str, Any]:
    """The fields of ``association.json`` that describe the run, not a scan."""
    return {
        "config": cfg.name,
        "config_hash": config_hash(cfg),
        "seed": seed,
        "method": method,
        "formation": cfg.targets.formation,
        "d_km": cfg.targets.spacing_km,
        "sigma_azimuth_mrad": cfg.noise.sigma_azimuth_mrad,
        "sigma_elevation_mrad": cfg.noise.sigma_elevation_mrad,
        "clutter": cfg.clutter.enabled,
        "sensors": [{"id": s.id, "position_km": list(s.position_km)} for s in cfg.sensors],
    }


def scan_record(
    scan: PassiveScan, params: AssocParams, method: str, truth: Scene | None, *, warm: bool = True
) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """Associate ``scan`` with ``METHODS[method]`` and triangulate its triples.

    Returns ``(record, positions (M, 3) km, covariances (M, 3, 3) km²)``; the covariance of a
    position is ``(Jᵀ R⁻¹ J)⁻¹`` at it (NaN where the geometry is degenerate).  ``truth``: the
    scene the lists were drawn from, for scoring (labels of each measurement, the true triples);
    without it (or when its lists are not exactly ``scan``'s) the record has no score.
    ``warm``: call the method once before the timed call (``time_s`` excludes first-call
    costs)."""
    fn = METHODS[method]
    if warm:
        fn(scan, params)
    t0 = time.perf_counter()
    a = fn(scan, params)
    dt = time.perf_counter() - t0
    Z = np.asarray(a.triples, dtype=np.intp).reshape(-1, 3)
    az = np.stack([scan.z[s][Z[:, s], 0] for s in range(3)], axis=1)
    el = np.stack([scan.z[s][Z[:, s], 1] for s in range(3)], axis=1)
    tri = triangulate(
        scan.sensors,
        az,
        el,
        np.ones(Z.shape, dtype=bool),
        params.sigma_azimuth,
        params.sigma_elevation,
        params.gn_steps,
    )
    cov = np.full((len(Z), 3, 3), np.nan)
    if len(Z):
        wa = 1.0 / np.asarray(params.sigma_azimuth) ** 2 * np.ones(Z.shape)
        we = 1.0 / np.asarray(params.sigma_elevation) ** 2 * np.ones(Z.shape)
        _, H, _ = _normal_eq(scan.sensors, tri.x, az, el, wa, we)
        for i in np.flatnonzero(tri.ok):
            cov[i] = np.linalg.inv(H[i])
    same = truth is not None and all(np.array_equal(truth.scan.z[s], scan.z[s]) for s in range(3))
    labels = truth.labels if same and truth is not None else None
    rec: dict[str, Any] = {
        "measurements": [
            [
                {"azimuth_rad": float(z[0]), "elevation_rad": float(z[1])}
                | ({"label": int(labels[s][n])} if labels is not None else {})
                for n, z in enumerate(scan.z[s])
            ]
            for s in range(3)
        ],
        "triples": Z.tolist(),
        "tuples": np.asarray(a.tuples).tolist(),
        "positions_km": tri.x.tolist(),
    }
    if same and truth is not None:
        g = {tuple(map(int, t)) for t in truth.truth}
        correct = [tuple(map(int, t)) in g for t in Z]
        target_of = [
            int(truth.labels[0][t[0]]) if ok else -1 for t, ok in zip(Z, correct, strict=True)
        ]
        hit, n_truth, n_out, exact = score(truth.truth, Z)
        rec |= {
            "targets_km": truth.targets.tolist(),
            "truth": truth.truth.tolist(),
            "truth_targets": truth.truth_targets.tolist(),
            "correct": correct,
            "target_of_triple": target_of,
            "score": {
                "correct": hit,
                "truth": n_truth,
                "output": n_out,
                "exact": exact,
                "p": hit / n_truth if n_truth else None,
                "precision": hit / n_out if n_out else None,
            },
        }
    rec |= {
        "cost": json_number(a.cost),
        "status": a.status,
        "message": a.message,
        "info": {k: json_number(v) for k, v in a.info.items()},
        "time_s": dt,
    }
    return rec, tri.x, cov
