"""The Monte Carlo evaluation of the mobile scenario: the same config over seeds 0..n−1.

Each seed is one in-process run (:func:`covnet.mobile.simulate.run`) in a worker process
(:func:`covnet.batches.pool.parallel_map`: *spawn* context, one worker per core by default),
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
from covnet.batches.pool import BatchInterrupted, parallel_map
from covnet.batches.stats import NONNEGATIVE, SHARE, Bounds, ci_half_width, seed_stats
from covnet.batches.trials import Batch, BatchProgress, Outcome, run_trials, trial_hash
from covnet.mobile.config import MobileConfig, config_hash, from_dict, normalised
from covnet.mobile.results import WORSE_TOL, decision_times, summarise
from covnet.mobile.simulate import run
from covnet.runs.rundir import RUN_INFO, utc_now, write_json

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


def _run_seed_list(task: tuple[Mapping[str, Any], list[int], str | None]) -> list[dict[str, Any]]:
    """The seeds of one task of the batch layer (:mod:`covnet.batches.trials`)."""
    data, seeds, solver = task
    return [run_seed(data, s, solver) for s in seeds]


POINT = "seeds"
"""The one point of a mobile Monte Carlo (its trials are the seeds)."""


def trial_key(cfg: MobileConfig, solver: str | None = None) -> str:
    """The hash that keys the Monte Carlo's trials: the config without its seed (each trial
    sets its own), and the solver."""
    data = normalised(cfg)
    data.pop("seed", None)
    return trial_hash("mc", {"config": data, "solver": solver})


def mc_outcome(
    cfg: MobileConfig,
    n: int,
    *,
    solver: str | None = None,
    out: Path | None = None,
    workers: int | None = None,
    cluster: str | None = None,
    progress: BatchProgress | None = None,
    ci_width: float | None = None,
    max_seeds: int | None = None,
    on_seed: Callable[[int], None] | None = None,
) -> tuple[list[int], list[dict[str, Any]], Outcome]:
    """``(seeds, summaries, outcome)``: seeds ``0, 1, ...`` (``n``, more with ``ci_width``:
    until the 95 % interval of the overall RMSE is narrower), each trial written to ``out`` as
    it finishes and skipped when there.  Ctrl-C: :class:`BatchInterrupted` with the seeds
    done (in seed order) as ``partial``: ``[(seed, summary), ...]``."""
    data = normalised(cfg)

    def headline(point: str, rows: list[dict[str, Any]]) -> float:
        return ci_half_width(seed_stats(r["overall"]["rmse_position_m"] for r in rows))

    b = Batch(
        "mc",
        _run_seed_list,
        lambda point, seeds: (data, seeds, solver),
        [POINT],
        first_seed=0,
        headline=headline,
        headline_name="overall RMSE (m)",
    )
    try:
        outcome = run_trials(
            b,
            n,
            out=out,
            key=trial_key(cfg, solver) if out is not None else None,
            workers=workers,
            cluster=cluster,
            progress=progress,
            ci_width=ci_width,
            max_seeds=max_seeds,
            on_task=None if on_seed is None else (lambda p, seeds: _each(on_seed, seeds)),
        )
    except BatchInterrupted as stop:
        stop.partial = sorted(((s, r) for (_, s), r in stop.done.items()), key=lambda sr: sr[0])
        # the seeds done from 0 on without a gap (what a Monte Carlo of fewer seeds is)
        run = [sr for i, sr in enumerate(stop.partial) if sr[0] == i]
        stop.partial = run
        raise
    rows = outcome.results[POINT]
    return b.seeds(outcome.seeds[POINT]), rows, outcome


def _each(fn: Callable[[int], None], seeds: list[int]) -> None:
    for s in seeds:
        fn(s)


def run_seeds(
    cfg: MobileConfig,
    seeds: Sequence[int],
    solver: str | None = None,
    workers: int | None = None,
    progress: McProgress | None = None,
) -> list[dict[str, Any]]:
    """Summaries of ``cfg`` run with each seed, in the order of ``seeds``.

    ``workers`` processes (default: the cores this process may use); ``workers=1`` runs in this
    process, without a pool.  Ctrl-C: :class:`covnet.batches.pool.BatchInterrupted`.
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


def _stats(values: Iterable[float | None], bounds: Bounds = NONNEGATIVE) -> dict[str, Any]:
    """Mean, standard deviation (ddof 0, as always), min, max over seeds, then the 95 %
    Student t interval of the mean (``ci_lo``, ``ci_hi``: from the sample standard deviation,
    ddof 1, within the quantity's ``bounds``: every one here is ``>= 0``, a rate within
    ``[0, 1]``; None with one seed) and ``n``: over the seeds where the value is defined (a
    rate over no scan is None), every entry None where it is defined in none."""
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    if v.size == 0:
        return dict.fromkeys(("mean", "std", "min", "max", "ci_lo", "ci_hi"), None) | {"n": 0}
    t = seed_stats(v, bounds)
    return {
        "mean": float(v.mean()),
        "std": float(v.std()),
        "min": float(v.min()),
        "max": float(v.max()),
        "ci_lo": t["ci_lo"],
        "ci_hi": t["ci_hi"],
        "n": t["n"],
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
_BOUNDS = {
    k: SHARE if "rate" in k or k == "miss_given_assigned" else NONNEGATIVE for k in _BLOCK_KEYS
}
"""The range of each: the rates within ``[0, 1]``, the rest ``>= 0``."""


def aggregate(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Mean, std, min, max over seeds of every metric; optimality pooled over decisions."""
    first = rows[0]
    agg: dict[str, Any] = {
        "targets": {
            t: {k: _stats((r["targets"][t][k] for r in rows), _BOUNDS[k]) for k in _BLOCK_KEYS}
            for t in first["target_ids"]
        },
        "overall": {k: _stats((r["overall"][k] for r in rows), _BOUNDS[k]) for k in _BLOCK_KEYS},
        "usage_cost_total": _stats(r["usage_cost_total"] for r in rows),
        "platform_travel_m": {
            s: _stats(r["platform_travel_m"][s] for r in rows) for s in first["platform_travel_m"]
        },
        "mode_conflicts_resolved": int(
            sum(r["decisions"]["mode_conflicts_resolved"] for r in rows)
        ),
    }
    opts = [r["optimality"] for r in rows if "optimality" in r]
    if opts:  # pooled over the decisions solved; every seed's time-outs counted
        gaps = np.concatenate([np.asarray(o["gaps"], dtype=np.float64) for o in opts])
        integ = [o["mean_integrality_gap"] for o in opts if o["mean_integrality_gap"] is not None]
        some = bool(gaps.size)
        agg["optimality"] = {
            "decisions": int(gaps.size),
            "share_lp_post_worse": float(np.mean(gaps > WORSE_TOL)) if some else None,
            "decisions_lp_post_worse": int(np.count_nonzero(gaps > WORSE_TOL)),
            "mean_gap": float(gaps.mean()) if some else None,
            "max_gap": float(gaps.max()) if some else None,
            "conflicts_resolved": int(sum(o["conflicts_resolved"] for o in opts)),
            "mean_integrality_gap": float(np.mean(integ)) if integ else None,
            "exact_not_optimal": int(sum(o["exact_not_optimal"] for o in opts)),
        }
    return agg


def write_mc(
    out_dir: Path,
    cfg: MobileConfig,
    seeds: Sequence[int],
    rows: Sequence[Mapping[str, Any]],
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write ``montecarlo.json`` (config hash, seeds, aggregate, per-seed summaries: what the
    config and seeds determine), ``config.json``, then ``run.json`` (the wall clock: each
    seed's decision times and the median over seeds of each part's median; last, as the
    batch's status that follows: with it the table is whole)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    rows, times = split_timing(rows)
    parts = times[0] if times else {}
    doc = {
        "kind": "mobile-montecarlo",
        "scenario": cfg.name,
        "config_hash": config_hash(cfg),
        "solver": rows[0]["solver"] if rows else cfg.solver,
        "seeds": list(seeds),
        "aggregate": aggregate(rows),
        "per_seed": list(rows),
        **(extra or {}),
    }
    write_json(out_dir / MC_FILE, doc)
    write_json(out_dir / "config.json", normalised(cfg))
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
    return doc
