"""The Monte Carlo evaluation protocol of spec §9: every cell (formation, d, σ, clutter) of the
config's grid, ``trials`` scans each, every method on the same scans.

Scans come from ``default_rng([seed, trial])`` (common random numbers: the same stream in every
cell, :mod:`covnet.passive.scene`).  Cells run in parallel on :func:`covnet.batch.parallel_map`
(spawn context); a cell's scans and methods run in one process, methods interleaved scan by scan, so
their timings see the same machine state.

Metrics, summed over a cell's runs (§9): ``p = Σ|Z ∩ G| / Σ|G|``, ``precision = Σ|Z ∩ G| / Σ|Z|``,
``exact_scan_rate`` = share of runs with ``Z = G``; ``median_time_s``: median wall time per scan
from the measurement lists to Z (statistics, triangulation and costs included, scene generation
excluded); for the cot method the mean candidate counts after the azimuth and elevation tests;
``sd_optimal_rate``: share of scans whose S-D cost equals the MILP optimum (S-D methods, when
``milp`` runs too).
"""

from __future__ import annotations

import math
import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from covnet.batch import BatchInterrupted, parallel_map
from covnet.core.passive.methods import METHODS
from covnet.passive.config import PassiveConfig, config_hash, normalised
from covnet.passive.scene import draw, score
from covnet.rundir import atomic_write, write_json

__all__ = [
    "RESULTS",
    "TABLE",
    "Cell",
    "grid",
    "run_cell",
    "run_grid",
    "table_markdown",
    "write_results",
]

RESULTS = "results.json"
TABLE = "results.md"
CONFIG = "config.json"
#: the S-D optimum is "reached" within this relative tolerance of the MILP objective
OPT_RTOL = 1e-6

Progress = Callable[[int, int, str], None]


@dataclass(frozen=True, slots=True)
class Cell:
    """One grid cell of §9."""

    formation: str
    d_km: float
    sigma_mrad: float
    clutter: bool

    @property
    def label(self) -> str:
        on = "on" if self.clutter else "off"
        return f"{self.formation} d={self.d_km:g} km σ={self.sigma_mrad:g} mrad clutter {on}"


def grid(cfg: PassiveConfig) -> list[Cell]:
    """The cells of ``cfg.montecarlo``, ordered formation, clutter, σ, d."""
    mc = cfg.montecarlo
    return [
        Cell(f, float(d), float(s), bool(c))
        for f in mc.formations
        for c in mc.clutter
        for s in mc.sigmas_mrad
        for d in mc.spacings_km
    ]


def run_cell(
    cfg: PassiveConfig, cell: Cell, trials: int, methods: Sequence[str]
) -> list[dict[str, Any]]:
    """Run ``trials`` scans of one cell with every method; one result row per method."""
    model = cfg.scene_model(cell.formation, cell.d_km, cell.sigma_mrad, cell.clutter)
    params = cfg.assoc_params(model)
    names = list(methods)
    hits = dict.fromkeys(names, 0)
    n_out = dict.fromkeys(names, 0)
    exact = dict.fromkeys(names, 0)
    failed = dict.fromkeys(names, 0)
    times: dict[str, list[float]] = {m: [] for m in names}
    costs: dict[str, list[float]] = {m: [] for m in names}
    extra: dict[str, dict[str, list[float]]] = {m: {} for m in names}
    n_truth = 0
    for trial in range(trials):
        scene = draw(model, cfg.seed, trial)
        n_truth += int(scene.truth.shape[0])
        for m in names:
            t0 = time.perf_counter()
            a = METHODS[m](scene.scan, params)
            times[m].append(time.perf_counter() - t0)
            h, _, z, is_exact = score(scene.truth, a.triples)
            hits[m] += h
            n_out[m] += z
            exact[m] += int(is_exact)
            failed[m] += int(a.status != 0)
            costs[m].append(a.cost)
            for key in ("n_azimuth", "n_elevation", "iterations", "n_tuples"):
                if key in a.info:
                    extra[m].setdefault(key, []).append(float(a.info[key]))
    rows = []
    for m in names:
        ex = extra[m]
        row: dict[str, Any] = {
            **asdict(cell),
            "method": m,
            "p": hits[m] / n_truth if n_truth else None,
            "precision": hits[m] / n_out[m] if n_out[m] else None,
            "exact_scan_rate": exact[m] / trials,
            "median_time_s": float(np.median(times[m])),
            "mean_candidates_azimuth": _mean(ex.get("n_azimuth")),
            "mean_candidates_elevation": _mean(ex.get("n_elevation")),
            "sd_optimal_rate": None,
            "mean_iterations": _mean(ex.get("iterations")),
            "mean_tuples": _mean(ex.get("n_tuples")),
            "trials": trials,
            "n_truth": n_truth,
            "n_correct": hits[m],
            "n_output": n_out[m],
            "solver_not_ok": failed[m],
        }
        if "milp" in names and m != "cot" and "n_tuples" in ex:
            ref = np.asarray(costs["milp"])
            c = np.asarray(costs[m])
            row["sd_optimal_rate"] = float(
                np.mean(c <= ref + OPT_RTOL * np.maximum(1.0, np.abs(ref)))
            )
        rows.append(row)
    return rows


def _mean(v: list[float] | None) -> float | None:
    return float(np.mean(v)) if v else None


def _run_cell_job(task: tuple[PassiveConfig, Cell, int, tuple[str, ...]]) -> list[dict[str, Any]]:
    return run_cell(*task)


def resolve_workers(requested: int, n_jobs: int) -> int:
    """``requested`` processes (0: every core), never more than there are jobs."""
    n = requested if requested > 0 else (os.cpu_count() or 1)
    return max(1, min(n, n_jobs))


def run_grid(
    cfg: PassiveConfig,
    trials: int | None = None,
    workers: int | None = None,
    progress: Progress | None = None,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Run every cell; returns the rows (grid order, then the config's method order) and the
    run facts (trials, workers, wall time, machine)."""
    n_trials = cfg.montecarlo.trials if trials is None else trials
    cells = grid(cfg)
    methods = tuple(cfg.montecarlo.methods)
    n_workers = resolve_workers(cfg.montecarlo.workers if workers is None else workers, len(cells))
    t0 = time.perf_counter()

    def on_done(n_done: int, n: int, i: int) -> None:
        if progress:
            progress(n_done, n, f"{cells[i].label} ({time.perf_counter() - t0:.0f} s so far)")

    tasks = [(cfg, cell, n_trials, methods) for cell in cells]
    try:
        results = parallel_map(_run_cell_job, tasks, n_workers, on_done)
    except BatchInterrupted as stop:  # the cells done, in grid order
        rows = [r for i in sorted(stop.done) for r in stop.done[i]]
        facts = _facts(n_trials, len(cells), methods, n_workers, t0)
        stop.partial = (rows, facts) if rows else None
        raise
    rows = [r for cell_rows in results for r in cell_rows]
    return rows, _facts(n_trials, len(cells), methods, n_workers, t0)


def _facts(
    n_trials: int, n_cells: int, methods: tuple[str, ...], n_workers: int, t0: float
) -> dict[str, Any]:
    """The run facts of :func:`run_grid`: what ran, on what, how long."""
    return {
        "trials": n_trials,
        "cells": n_cells,
        "methods": list(methods),
        "workers": n_workers,
        "wall_s": time.perf_counter() - t0,
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "numpy": np.__version__,
        },
    }


def _fmt(v: Any, spec: str) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return format(v, spec)


def table_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The result rows as one Markdown table."""
    head = (
        "| formation | d (km) | σ (mrad) | clutter | method | p | precision | exact scans | "
        "median time (ms) | cand. after azimuth | cand. after elevation | S-D optimum |\n"
        "|---|---:|---:|---|---|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    lines = []
    for r in rows:
        t_ms = 1e3 * r["median_time_s"]
        lines.append(
            f"| {r['formation']} | {r['d_km']:g} | {r['sigma_mrad']:g} | "
            f"{'on' if r['clutter'] else 'off'} | {r['method']} | {_fmt(r['p'], '.3f')} | "
            f"{_fmt(r['precision'], '.3f')} | {_fmt(r['exact_scan_rate'], '.2f')} | "
            f"{t_ms:.3f} | {_fmt(r['mean_candidates_azimuth'], '.1f')} | "
            f"{_fmt(r['mean_candidates_elevation'], '.1f')} | {_fmt(r['sd_optimal_rate'], '.2f')} |"
        )
    return head + "\n".join(lines) + "\n"


def write_results(
    out_dir: Path, cfg: PassiveConfig, rows: Sequence[dict[str, Any]], facts: dict[str, Any]
) -> dict[str, Any]:
    """Write ``results.json``, ``results.md`` and ``config.json`` (atomically); return the
    results document."""

    out_dir.mkdir(parents=True, exist_ok=True)
    doc: dict[str, Any] = {
        "kind": "passive-montecarlo",
        "config": cfg.name,
        "config_hash": config_hash(cfg),
        "seed": cfg.seed,
        **facts,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "rows": list(rows),
    }
    write_json(out_dir / CONFIG, normalised(cfg))
    title = (
        f"# Passive association, Monte Carlo ({cfg.name}, config {doc['config_hash']}, "
        f"seed {cfg.seed}, {facts['trials']} trials per cell)\n\n"
        f"Times are medians per scan on {facts['machine']['processor']} "
        f"({facts['workers']} worker processes); compare methods by ratios only.\n\n"
    )
    atomic_write(out_dir / TABLE, (title + table_markdown(rows)).encode())
    write_json(out_dir / RESULTS, doc)
    return doc
