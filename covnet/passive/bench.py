"""``covnet bench passive``: median time per scan of every association method on the spec's
scenes, measured in one run.

Scenes (spec §2, §9): both formations × d ∈ {0.5, 1, 2} km × σ ∈ {1, 3} mrad × clutter off/on,
``scans`` scans each, drawn once (scene generation is not timed).  Every scan is given to every
method, in an order rotated scan by scan, so all methods see the same machine state; after a
warm-up, each call is timed with ``time.perf_counter`` from the measurement lists to Z.

Goal (issue 6): the cot method at least 3× faster than Lagrangian relaxation at equal accuracy
for d ≥ 1 km.  The report states the ratio and the accuracies side by side, whatever they are.
"""

from __future__ import annotations

import gc
import os
import platform
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from covnet.core.passive.methods import METHODS
from covnet.passive.config import PassiveConfig, from_dict
from covnet.passive.scene import FORMATIONS, PAPER_SENSORS, draw, score

__all__ = ["DEFAULT_SCANS", "GOAL_RATIO", "bench_config", "run"]

DEFAULT_SCANS = 40
GOAL_RATIO = 3.0
SPACINGS = (0.5, 1.0, 2.0)
SIGMAS = (1.0, 3.0)
WARMUP = 5


def bench_config(seed: int = 2026) -> PassiveConfig:
    """The spec's setup with every default (paper layout, clutter 0.95 / 0.25 / 0.1 rad)."""
    return from_dict(
        {
            "kind": "passive",
            "name": "bench",
            "seed": seed,
            "sensors": [
                {"id": f"s{i + 1}", "position_km": [float(v) for v in PAPER_SENSORS[i]]}
                for i in range(3)
            ],
        },
        "<bench>",
    )


def run(
    scans: int | None = None,
    methods: tuple[str, ...] | None = None,
    progress: Callable[[str], None] | None = None,
    seed: int = 2026,
) -> dict[str, Any]:
    """Time every method on every scene; returns ``{"rows": [...], "summary": {...}}``.

    ``scans`` per scene (default :data:`DEFAULT_SCANS`).  A row per (method, d, clutter), with
    ``None`` meaning pooled (per d over clutter off/on; and over everything): ``median_s`` over
    the scans of both formations and both σ, ``p`` (correct association rate), ``n_scans``.
    The summary compares cot with lr for d ≥ 1 km: ``ratio`` = median lr time / median cot
    time, with both p, clean and clutter.
    """
    scans = DEFAULT_SCANS if scans is None else scans
    cfg = bench_config(seed)
    names = tuple(methods or METHODS)
    cases = []
    scene = 0
    for f in FORMATIONS:
        for d in SPACINGS:
            for s in SIGMAS:
                for c in (False, True):
                    model = cfg.scene_model(f, d, s, c)
                    params = cfg.assoc_params(model)
                    for t in range(scans):
                        # independent draws per scene (no common random numbers here), so
                        # the pooled accuracies are not one sample seen many times
                        sc = draw(model, seed, scene * scans + t)
                        cases.append((d, c, sc.scan, params, sc.truth, f))
                    scene += 1
    for case in cases[:WARMUP]:
        for m in names:
            METHODS[m](case[2], case[3])
    times = {m: np.empty(len(cases)) for m in names}
    hits = {m: np.empty(len(cases), dtype=np.intp) for m in names}
    n_truth = np.array([c[4].shape[0] for c in cases])
    if progress:
        progress(f"timing {len(names)} methods on {len(cases)} scans ...")
    gc_was = gc.isenabled()
    gc.disable()
    try:
        for n, (_, _, scan, params, truth, _) in enumerate(cases):
            k = n % len(names)
            for m in names[k:] + names[:k]:
                t0 = time.perf_counter()
                a = METHODS[m](scan, params)
                times[m][n] = time.perf_counter() - t0
                hits[m][n] = score(truth, a.triples)[0]
    finally:
        if gc_was:
            gc.enable()
    d_arr = np.array([c[0] for c in cases])
    c_arr = np.array([c[1] for c in cases])
    f_arr = np.array([c[5] for c in cases])
    rows = []
    every = np.ones(len(cases), dtype=bool)
    for m in names:
        for dd in (*SPACINGS, None):
            for cc in (False, True, None):
                if dd is None and cc is not None:
                    continue
                sel = (every if dd is None else d_arr == dd) & (
                    every if cc is None else c_arr == cc
                )
                rows.append(
                    {
                        "method": m,
                        "d_km": dd,
                        "clutter": cc,
                        "median_s": float(np.median(times[m][sel])),
                        "p": float(hits[m][sel].sum() / n_truth[sel].sum()),
                        "n_scans": int(sel.sum()),
                    }
                )
    summary: dict[str, Any] = {
        "scans_per_scene": scans,
        "scenes": len(cases) // scans,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "goal_ratio": GOAL_RATIO,
    }
    if "cot" in names and "lr" in names:
        far = d_arr >= 1.0
        ratio = float(np.median(times["lr"][far]) / np.median(times["cot"][far]))
        acc = {}
        groups = [("clean", far & ~c_arr), ("clutter", far & c_arr), ("all", far)]
        groups += [
            (f"{kind} {f}", sel & (f_arr == f)) for kind, sel in groups[:2] for f in FORMATIONS
        ]
        for label, sel in groups:
            acc[label] = {m: float(hits[m][sel].sum() / n_truth[sel].sum()) for m in ("cot", "lr")}
        summary |= {"ratio_lr_over_cot_d_ge_1": ratio, "p_d_ge_1": acc}
        summary["speed_goal_met"] = ratio >= GOAL_RATIO
    return {"rows": rows, "summary": summary}
