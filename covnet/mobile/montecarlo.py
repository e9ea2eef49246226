"""The Monte Carlo evaluation of the mobile scenario: the same config over seeds 0..n−1.

Each seed is one in-process run (:func:`covnet.mobile.simulate.run`) in a worker process
(:func:`covnet.batch.parallel_map`: *spawn* context, one worker per core by default),
summarised there (:func:`covnet.mobile.results.summarise`, without the per-decision lists), and
sent back as a small dict.  The results are ordered by seed whatever order the workers finish
in, so ``montecarlo.json`` depends only on the config and the seeds; the wall times (each seed's
decision times and their medians over seeds) go to ``run.json``.

Aggregates (``aggregate``): for every scalar metric of the per-run summary, the mean, standard
deviation (ddof = 0), min and max over seeds; the optimality counts are pooled over all decisions
of all seeds (share of decisions where the LP + post-step is worse than the MILP, mean and max
gap, conflicts resolved).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from covnet import __version__
from covnet.batch import BatchInterrupted, parallel_map
from covnet.mobile.config import MobileConfig, config_hash, from_dict, normalised
from covnet.mobile.results import WORSE_TOL, decision_times, summarise
from covnet.mobile.simulate import run
from covnet.rundir import RUN_INFO, utc_now, write_json

MC_FILE = "montecarlo.json"
#: progress(done, total, seed) after each finished seed
McProgress = Callable[[int, int, int], None]


def run_seed(cfg_data: Mapping[str, Any], seed: int, solver: str | None) -> dict[str, Any]:
    """One seed in a worker: validate, simulate, summarise (top level so it pickles); the
    summary, with the seed's decision times under ``decision_time_s`` (:func:`split_timing`
    takes them out)."""
    cfg = from_dict({**cfg_data, "seed": seed}, f"seed {seed}")
    r = run(cfg, solver)
    s = summarise(cfg, r)
    opt = s.get("optimality")
    if opt is not None:
        per = opt.pop("per_decision")
        opt["gaps"] = [g for g in per["gap"] if g is not None]
    s["decision_time_s"] = decision_times(r)
    return s


def split_timing(
    rows: Sequence[Mapping[str, Any]],
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """``(summaries, decision times)`` of :func:`run_seed`'s rows."""
    summaries = [{k: v for k, v in r.items() if k != "decision_time_s"} for r in rows]
    return summaries, [dict(r["decision_time_s"]) for r in rows]


def _run_seed_task(task: tuple[Mapping[str, Any], int, str | None]) -> dict[str, Any]:
    return run_seed(*task)


def run_seeds(
    cfg: MobileConfig,
    seeds: Sequence[int],
    solver: str | None = None,
    workers: int | None = None,
    progress: McProgress | None = None,
) -> list[dict[str, Any]]:
    """Summaries of ``cfg`` run with each seed, in the order of ``seeds``.

    ``workers`` processes (default: the cores this process may use); ``workers=1`` runs in this
    process, without a pool.  Ctrl-C: :class:`covnet.batch.BatchInterrupted`.
    """
    data = normalised(cfg)
    seeds = list(seeds)

    def on_done(done: int, n: int, i: int) -> None:
        if progress is not None:
            progress(done, n, seeds[i])

    try:
        return parallel_map(_run_seed_task, [(data, s, solver) for s in seeds], workers, on_done)
    except BatchInterrupted as stop:  # the seeds done, in seed order
        stop.partial = [(seeds[i], stop.done[i]) for i in sorted(stop.done)]
        raise


def _stats(values: Iterable[float]) -> dict[str, float]:
    v = np.asarray(list(values), dtype=np.float64)
    return {
        "mean": float(v.mean()),
        "std": float(v.std()),
        "min": float(v.min()),
        "max": float(v.max()),
    }


_BLOCK_KEYS = (
    "rmse_position_m",
    "rmse_position_second_half_m",
    "missed_detection_rate",
    "missed_detection_rate_first_half",
    "missed_detection_rate_second_half",
    "miss_given_assigned",
    "unobserved_scans",
)


def aggregate(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Mean, std, min, max over seeds of every metric; optimality pooled over decisions."""
    first = rows[0]
    agg: dict[str, Any] = {
        "targets": {
            t: {k: _stats(r["targets"][t][k] for r in rows) for k in _BLOCK_KEYS}
            for t in first["target_ids"]
        },
        "overall": {k: _stats(r["overall"][k] for r in rows) for k in _BLOCK_KEYS},
        "usage_cost_total": _stats(r["usage_cost_total"] for r in rows),
        "platform_travel_m": {
            s: _stats(r["platform_travel_m"][s] for r in rows) for s in first["platform_travel_m"]
        },
        "mode_conflicts_resolved": int(
            sum(r["decisions"]["mode_conflicts_resolved"] for r in rows)
        ),
    }
    if all("optimality" in r for r in rows):
        gaps = np.concatenate([np.asarray(r["optimality"]["gaps"], dtype=np.float64) for r in rows])
        agg["optimality"] = {
            "decisions": int(gaps.size),
            "share_lp_post_worse": float(np.mean(gaps > WORSE_TOL)),
            "decisions_lp_post_worse": int(np.count_nonzero(gaps > WORSE_TOL)),
            "mean_gap": float(gaps.mean()),
            "max_gap": float(gaps.max()),
            "conflicts_resolved": int(sum(r["optimality"]["conflicts_resolved"] for r in rows)),
            "mean_integrality_gap": float(
                np.mean([r["optimality"]["mean_integrality_gap"] for r in rows])
            ),
            "exact_not_optimal": int(sum(r["optimality"]["exact_not_optimal"] for r in rows)),
        }
    return agg


def write_mc(
    out_dir: Path, cfg: MobileConfig, seeds: Sequence[int], rows: Sequence[Mapping[str, Any]]
) -> dict[str, Any]:
    """Write ``montecarlo.json`` (config hash, seeds, aggregate, per-seed summaries: what the
    config and seeds determine) and ``run.json`` (the wall clock: each seed's decision times
    and the median over seeds of each part's median)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    rows, times = split_timing(rows)
    parts = times[0] if times else {}
    write_json(
        out_dir / RUN_INFO,
        {
            "created_utc": utc_now(),
            "covnet_version": __version__,
            "kind": "mobile-montecarlo",
            "decision_time_median_s": {
                part: float(np.median([t[part]["median"] for t in times])) for part in parts
            },
            "decision_time_s": dict(zip((str(s) for s in seeds), times, strict=True)),
        },
    )
    doc = {
        "kind": "mobile-montecarlo",
        "scenario": cfg.name,
        "config_hash": config_hash(cfg),
        "solver": rows[0]["solver"] if rows else cfg.solver,
        "seeds": list(seeds),
        "aggregate": aggregate(rows),
        "per_seed": list(rows),
    }
    write_json(out_dir / MC_FILE, doc)
    write_json(out_dir / "config.json", normalised(cfg))
    return doc
