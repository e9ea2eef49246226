"""The Monte Carlo evaluation protocol of spec §9: every cell (formation, d, σ, clutter) of the
config's grid, ``trials`` scans each, every method on the same scans.

Scans come from ``default_rng([seed, trial])`` (common random numbers: the same stream in every
cell, :mod:`covnet.passive.scene`).  Cells run in parallel on
:func:`covnet.batches.pool.parallel_map`
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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from covnet.batches.pool import BatchInterrupted
from covnet.batches.stats import SHARE, add_stats, ci_half_width, count_range, seed_stats
from covnet.batches.trials import (
    Batch,
    BatchProgress,
    Outcome,
    complete_points,
    point_key,
    run_trials,
    trial_hash,
)
from covnet.core.passive.methods import METHODS
from covnet.passive.config import PassiveConfig, config_hash, normalised
from covnet.passive.scene import draw, score
from covnet.runs.rundir import atomic_write, write_json

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


_EXTRA_KEYS = ("n_azimuth", "n_elevation", "iterations", "n_tuples")


def run_cell_trials(
    cfg: PassiveConfig, cell: Cell, trials: Sequence[int], methods: Sequence[str]
) -> list[dict[str, Any]]:
    """The scans ``trials`` of one cell with every method, methods interleaved scan by scan:
    one record per trial (``n_truth``; per method ``hit``, ``out``, ``exact``, ``failed``,
    ``cost``, ``time_s`` and the method's counts), what :func:`cell_rows` sums."""
    model = cfg.scene_model(cell.formation, cell.d_km, cell.sigma_mrad, cell.clutter)
    params = cfg.assoc_params(model)
    records = []
    for trial in trials:
        scene = draw(model, cfg.seed, trial)
        per: dict[str, Any] = {}
        for m in methods:
            t0 = time.perf_counter()
            a = METHODS[m](scene.scan, params)
            dt = time.perf_counter() - t0
            h, _, z, is_exact = score(scene.truth, a.triples)
            per[m] = {
                "hit": int(h),
                "out": int(z),
                "exact": bool(is_exact),
                "failed": int(a.status != 0),
                "cost": float(a.cost),
                "time_s": dt,
                "extra": {k: float(a.info[k]) for k in _EXTRA_KEYS if k in a.info},
            }
        records.append({"trial": int(trial), "n_truth": int(scene.truth.shape[0]), "m": per})
    return records


def cell_rows(
    cell: Cell, records: Sequence[dict[str, Any]], methods: Sequence[str]
) -> list[dict[str, Any]]:
    """One result row per method from a cell's trial records (in trial order): the sums and
    means of §9 (the numbers of one run over every trial), then the statistics over trials
    (``p_trial_*``: of each trial's share of targets associated; ``exact_scan_*``; 95 %
    Student t intervals, :func:`covnet.batches.stats.add_stats`)."""
    names = list(methods)
    trials = len(records)
    n_truth = sum(int(r["n_truth"]) for r in records)
    rows = []
    for m in names:
        recs = [r["m"][m] for r in records]
        hits = sum(int(x["hit"]) for x in recs)
        n_out = sum(int(x["out"]) for x in recs)
        exact = sum(int(bool(x["exact"])) for x in recs)
        failed = sum(int(x["failed"]) for x in recs)
        ex: dict[str, list[float]] = {}
        for x in recs:
            for key in _EXTRA_KEYS:
                if key in x["extra"]:
                    ex.setdefault(key, []).append(float(x["extra"][key]))
        row: dict[str, Any] = {
            **asdict(cell),
            "method": m,
            "p": hits / n_truth if n_truth else None,
            "precision": hits / n_out if n_out else None,
            "exact_scan_rate": exact / trials,
            "median_time_s": float(np.median([x["time_s"] for x in recs])),
            "mean_candidates_azimuth": _mean(ex.get("n_azimuth")),
            "mean_candidates_elevation": _mean(ex.get("n_elevation")),
            "sd_optimal_rate": None,
            "mean_iterations": _mean(ex.get("iterations")),
            "mean_tuples": _mean(ex.get("n_tuples")),
            "trials": trials,
            "n_truth": n_truth,
            "n_correct": hits,
            "n_output": n_out,
            "solver_not_ok": failed,
        }
        if "milp" in names and m != "cot" and "n_tuples" in ex:
            ref = np.asarray([r["m"]["milp"]["cost"] for r in records])
            c = np.asarray([x["cost"] for x in recs])
            row["sd_optimal_rate"] = float(
                np.mean(c <= ref + OPT_RTOL * np.maximum(1.0, np.abs(ref)))
            )
        add_stats(row, "p_trial", _p_trials(records, m), SHARE)
        add_stats(row, "exact_scan", [float(bool(x["exact"])) for x in recs], SHARE)
        rows.append(row)
    return rows


def _p_trials(records: Sequence[dict[str, Any]], method: str) -> list[float]:
    """Each trial's share of its targets that ``method`` associated (trials with none left
    out)."""
    return [r["m"][method]["hit"] / r["n_truth"] for r in records if r["n_truth"]]


def run_cell(
    cfg: PassiveConfig, cell: Cell, trials: int, methods: Sequence[str]
) -> list[dict[str, Any]]:
    """Run ``trials`` scans of one cell with every method; one result row per method."""
    return cell_rows(cell, run_cell_trials(cfg, cell, range(trials), methods), methods)


def _mean(v: list[float] | None) -> float | None:
    return float(np.mean(v)) if v else None


def _run_trials_job(
    task: tuple[PassiveConfig, Cell, list[int], tuple[str, ...]],
) -> list[dict[str, Any]]:
    """A task of the batch layer (:mod:`covnet.batches.trials`): trials of one cell."""
    return run_cell_trials(*task)


def cell_key(cell: Cell) -> str:
    """A cell as a point key of the trial store."""
    return point_key(asdict(cell))


def trial_key(cfg: PassiveConfig) -> str:
    """The hash that keys the protocol's trials: the config without the trial count and the
    worker count (which change no trial)."""
    data = normalised(cfg)
    data["montecarlo"] = {
        k: v for k, v in data["montecarlo"].items() if k not in ("trials", "workers")
    }
    return trial_hash("mc", {"config": data})


def resolve_workers(requested: int, n_jobs: int) -> int:
    """``requested`` processes (0: every core), never more than there are jobs."""
    n = requested if requested > 0 else (os.cpu_count() or 1)
    return max(1, min(n, n_jobs))


def run_grid(
    cfg: PassiveConfig,
    trials: int | None = None,
    workers: int | None = None,
    progress: Progress | None = None,
    **kw: Any,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """:func:`run_grid_outcome`'s rows and run facts."""
    rows, facts, _ = run_grid_outcome(cfg, trials, workers, progress, **kw)
    return rows, facts


def run_grid_outcome(
    cfg: PassiveConfig,
    trials: int | None = None,
    workers: int | None = None,
    progress: Progress | None = None,
    *,
    out: Path | None = None,
    cluster: str | None = None,
    batch_progress: BatchProgress | None = None,
    ci_width: float | None = None,
    max_seeds: int | None = None,
) -> tuple[list[dict[str, Any]], dict[str, Any], Outcome]:
    """Run every cell; returns the rows (grid order, then the config's method order) and the
    run facts (trials, workers, wall time, machine).  A cell's trials are one task (its
    ``trials`` scans; with ``ci_width`` more batches of them, until every cell's interval of
    the per-trial share associated is narrower, for every method); each task is written to
    ``out``'s trial store as it finishes and skipped when there (:mod:`covnet.batches.trials`)."""
    n_trials = cfg.montecarlo.trials if trials is None else trials
    cells = grid(cfg)
    methods = tuple(cfg.montecarlo.methods)
    n_workers = resolve_workers(cfg.montecarlo.workers if workers is None else workers, len(cells))
    t0 = time.perf_counter()
    by_key = {cell_key(c): c for c in cells}
    done_cells = [0]

    def on_task(key: str, seeds: list[int]) -> None:
        done_cells[0] += 1
        if progress:
            progress(
                done_cells[0],
                len(cells),
                f"{by_key[key].label} ({time.perf_counter() - t0:.0f} s so far)",
            )

    def headline(key: str, records: list[dict[str, Any]]) -> float:
        return max(ci_half_width(seed_stats(_p_trials(records, m))) for m in methods)

    b = Batch(
        "mc",
        _run_trials_job,
        lambda key, seeds: (cfg, by_key[key], seeds, methods),
        list(by_key),
        first_seed=0,
        group=max(1, n_trials),
        headline=headline,
        headline_name="share of targets associated (p, per trial)",
    )
    try:
        outcome = run_trials(
            b,
            n_trials,
            out=out,
            key=trial_key(cfg) if out is not None else None,
            workers=None if cluster else n_workers,
            cluster=cluster,
            progress=batch_progress,
            ci_width=ci_width,
            max_seeds=max_seeds,
            on_task=on_task,
        )
    except BatchInterrupted as stop:  # the cells done, in grid order
        done = complete_points(b, stop.done, n_trials)
        rows = [r for k, recs in done.items() for r in cell_rows(by_key[k], recs, methods)]
        facts = _facts(n_trials, len(cells), methods, None if cluster else n_workers, t0, cluster)
        stop.partial = (rows, facts) if rows else None
        raise
    rows = [r for k, recs in outcome.results.items() for r in cell_rows(by_key[k], recs, methods)]
    # on a cluster, its workers (the scheduler's count), not this machine's pool it never used
    used = outcome.backend.get("workers") if cluster else n_workers
    facts = _facts(n_trials, len(cells), methods, used, t0, cluster)
    facts.update(outcome.ci_facts())
    ran = sorted({len(recs) for recs in outcome.results.values()})
    if ran and ran != [n_trials]:  # --ci-width added trials to some cells: say how many
        facts["trials_range"] = [ran[0], ran[-1]]
    return rows, facts, outcome


def trials_text(facts: Mapping[str, Any]) -> str:
    """``"6"``, or ``"12-18"`` where ``--ci-width`` gave the cells different counts (the
    summary line and ``results.md`` said the first round's 6)."""
    return count_range(facts.get("trials_range") or (facts["trials"],))


def _facts(
    n_trials: int,
    n_cells: int,
    methods: tuple[str, ...],
    n_workers: int | None,
    t0: float,
    cluster: str | None = None,
) -> dict[str, Any]:
    """The run facts of :func:`run_grid`: what ran, on what, how long.  ``n_workers``: the
    local pool's processes, or with ``cluster`` (its scheduler's address, then in the facts
    too) the cluster's workers (``None``: not known); ``machine`` is always this one's."""
    return {
        "trials": n_trials,
        "cells": n_cells,
        "methods": list(methods),
        "workers": n_workers,
        **({"cluster": cluster} if cluster else {}),
        "wall_s": time.perf_counter() - t0,
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "numpy": np.__version__,
        },
    }


def where_it_ran(facts: Mapping[str, Any]) -> str:
    """``"x86_64 (2 worker processes)"`` or, on a cluster, ``"the Dask cluster tcp://...
    (1 worker)"`` (its machines are not this one: no processor named)."""
    n = facts.get("workers")
    if facts.get("cluster"):
        count = "workers not known" if n is None else f"{n} worker{'s' if n != 1 else ''}"
        return f"the Dask cluster {facts['cluster']} ({count})"
    return f"{facts['machine']['processor']} ({n} worker processes)"


def _fmt(v: Any, spec: str) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return format(v, spec)


def _ci(row: dict[str, Any], name: str) -> str:
    """``mean [lo, hi]`` of a row's statistics over trials (– without them)."""
    mean, lo, hi = (row.get(f"{name}_{k}") for k in ("mean", "ci_lo", "ci_hi"))
    if mean is None:
        return "–"
    return f"{mean:.3f}" if lo is None else f"{mean:.3f} [{lo:.3f}, {hi:.3f}]"


def table_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The result rows as one Markdown table."""
    head = (
        "| formation | d (km) | σ (mrad) | clutter | method | p | p per trial (95 % CI) | "
        "precision | exact scans | median time (ms) | cand. after azimuth | "
        "cand. after elevation | S-D optimum |\n"
        "|---|---:|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    lines = []
    for r in rows:
        t_ms = 1e3 * r["median_time_s"]
        lines.append(
            f"| {r['formation']} | {r['d_km']:g} | {r['sigma_mrad']:g} | "
            f"{'on' if r['clutter'] else 'off'} | {r['method']} | {_fmt(r['p'], '.3f')} | "
            f"{_ci(r, 'p_trial')} | "
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
        f"seed {cfg.seed}, {trials_text(facts)} trials per cell)\n\n"
        f"Times are medians per scan on {where_it_ran(facts)}; compare methods by ratios "
        "only.\n\n"
    )
    atomic_write(out_dir / TABLE, (title + table_markdown(rows)).encode())
    write_json(out_dir / RESULTS, doc)
    return doc
