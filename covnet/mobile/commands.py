"""The mobile kind's commands (registered by :mod:`covnet.mobile.kind`):

* ``covnet run configs/mobile.yaml [--solver lp|milp] [--seed S]``  -> :func:`run`
* ``covnet mc configs/mobile.yaml [--trials 20] [--out DIR]``       -> :func:`mc`
* ``covnet bench mobile [--json]``                                  -> :func:`bench`
* after ``covnet up configs/mobile.yaml``                           -> :func:`after_up`

Each returns an exit status and prints like the other commands; a user's mistake raises
:class:`~covnet.errors.UsageError` (exit status 2).
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from covnet.batches.pool import BatchInterrupted, default_workers, end_batch, finish_batch
from covnet.batches.stats import CUT, plus_minus
from covnet.batches.trials import BatchProgress, batch_options, prepare_batch_out, write_batch_info
from covnet.errors import UsageError
from covnet.mobile.config import MobileConfig
from covnet.mobile.montecarlo import MC_FILE, mc_outcome, trial_key, write_mc
from covnet.mobile.results import load_summary, write_run
from covnet.mobile.simulate import run as simulate
from covnet.runs.rundir import RUN_INFO, after_the_results, read_json

# The figure (matplotlib) and the benchmark are imported by the commands that use them:
# start-up time of the others.

EXIT_OK = 0


def _pm(st: dict[str, Any]) -> str:
    """``mean±half-width`` of an aggregate's statistics (the mean alone with one seed)."""
    return plus_minus(st["mean"], st.get("ci_lo"), st.get("ci_hi"), ".2f", "±")


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100.0 * x:.1f} %"


def _none_solved_text(opt: dict[str, Any]) -> str:
    """The optimality line of a run or batch whose every compared MILP timed out."""
    return (
        f"  optimality: no MILP proved an optimum within its time limit "
        f"({opt['exact_not_optimal']} compared decisions left out)"
    )


def print_summary(out: Path, s: dict[str, Any]) -> None:
    """The run's headline numbers (the ``covnet run`` style)."""
    print(
        f"run directory: {out}  (config {s['config_hash']}, seed {s['seed']}, solver {s['solver']})"
    )
    for tid, b in s["targets"].items():
        print(
            f"  {tid:>6}: position RMSE {b['rmse_position_m']:6.2f} m "
            f"(2nd half {b['rmse_position_second_half_m']:5.2f} m), "
            f"missed {_pct(b['missed_detection_rate'])} "
            f"(2nd half {_pct(b['missed_detection_rate_second_half'])}), "
            f"unobserved {b['unobserved_scans']} scans"
        )
    ov = s["overall"]
    print(
        f"  overall: RMSE {ov['rmse_position_m']:.2f} m (2nd half "
        f"{ov['rmse_position_second_half_m']:.2f} m), missed {_pct(ov['missed_detection_rate'])} "
        f"(2nd half {_pct(ov['missed_detection_rate_second_half'])}), usage cost "
        f"{s['usage_cost_total']:.1f}, platform travel {s['platform_travel_m']['total']:.0f} m"
    )
    opt = s.get("optimality")
    if opt is not None and not opt["decisions"]:
        print(_none_solved_text(opt))
    elif opt is not None:
        worse = round(opt["share_lp_post_worse"] * opt["decisions"])
        print(
            f"  optimality: LP + post-step worse than the MILP in {worse}/{opt['decisions']} "
            f"decisions, mean gap {100 * opt['mean_gap']:.4f} %, max gap "
            f"{100 * opt['max_gap']:.2f} %, {opt['conflicts_resolved']} mode conflicts resolved"
            + _not_optimal_text(opt)
        )
    info = out / RUN_INFO
    t = read_json(info).get("decision_time_s") if info.is_file() else None
    if t:
        parts = ", ".join(f"{k} {1e3 * v['median']:.2f} ms" for k, v in t.items())
        print(f"  decision time (median): {parts}")


def run(cfg: MobileConfig, out_dir: Path, *, figures: bool = True) -> int:
    """``covnet run configs/mobile.yaml [--solver NAME] [--seed S] [--out DIR]``: one in-process
    run; writes the run directory and the figure."""
    t0 = time.perf_counter()
    r = simulate(cfg)
    extra = " (with the exact comparison)" if cfg.compare_exact else ""
    print(f"{r.solver:>10}: {cfg.scans} scans in {time.perf_counter() - t0:.2f} s{extra}")
    summary = write_run(out_dir, cfg, r)
    print_summary(out_dir, summary)
    if figures:
        from covnet.mobile.plots import make_figure  # matplotlib: start-up

        print(f"figure: {make_figure(out_dir)}")
    return EXIT_OK


def after_up(cfg: MobileConfig, out: Path, *, figures: bool) -> None:
    """After ``covnet up``: the figure and the summary of the scans done."""
    if not (out / "summary.json").is_file():
        return
    if figures:
        from covnet.mobile.plots import make_figure  # matplotlib: start-up

        print(f"figure: {make_figure(out)}")
    print_summary(out, load_summary(out))


def mc(args: Any, cfg: MobileConfig) -> int:
    """``covnet mc configs/mobile.yaml [--trials N] [--out DIR] [--force] [--workers W]
    [--cluster ADDRESS] [--ci-width X [--max-seeds N]]``."""
    seeds = args.trials if args.trials is not None else 20
    if seeds < 1:
        raise UsageError(f"--trials: must be >= 1, got {seeds}")
    if getattr(args, "seed", None) is not None:
        raise UsageError(
            "--seed: a mobile Monte Carlo runs seeds 0..N-1 (--trials N), whatever the "
            "config's seed; covnet run --seed runs one of them"
        )
    opts = batch_options(args, seeds)
    return mc_run(
        cfg,
        args.out,
        seeds,
        force=args.force,
        workers=opts.workers,
        cluster=opts.cluster,
        ci_width=opts.ci_width,
        max_seeds=opts.max_seeds,
        figures=not getattr(args, "no_figures", False),
        json_out=getattr(args, "json", False),
    )


def mc_run(
    cfg: MobileConfig,
    out: str | Path | None,
    seeds: int = 20,
    progress: bool | Callable[[int, int, int], None] = True,
    *,
    workers: int | None = None,
    force: bool = False,
    cluster: str | None = None,
    ci_width: float | None = None,
    max_seeds: int | None = None,
    figures: bool = True,
    json_out: bool = False,
) -> int:
    """``covnet mc configs/mobile.yaml [--trials 20] [--out DIR]``: seeds ``0..seeds-1`` in
    parallel worker processes (one per core by default) or on a Dask cluster; each seed
    written to ``OUT/trials`` as it finishes (the same command resumes); writes
    ``montecarlo.json``.

    ``progress``: ``True`` shows one live progress line on stderr, ``False`` nothing, or a
    callable ``(done, total, seed)`` of the caller's, called after each seed run here.
    """
    if seeds < 1:
        raise UsageError(f"--trials: must be >= 1, got {seeds}")
    key = trial_key(cfg)
    out_dir, _ = prepare_batch_out(out, f"{cfg.name}-mc", force, "mc", key)
    write_batch_info(out_dir, "mc", key, {})
    n_workers = min(workers or default_workers(), seeds)
    t0 = time.perf_counter()
    if progress is True:
        where = f"the Dask cluster {cluster}" if cluster else f"{n_workers} worker process(es)"
        print(
            f"{cfg.name}: {seeds} seeds x {cfg.scans} scans, solver {cfg.solver}, {where}",
            file=sys.stderr,
            flush=True,
        )
    done = [0]

    def on_seed(seed: int) -> None:
        done[0] += 1
        if callable(progress):
            progress(done[0], seeds, seed)

    try:
        seed_list, rows, outcome = mc_outcome(
            cfg,
            seeds,
            out=out_dir,
            workers=None if cluster else n_workers,
            cluster=cluster,
            progress=BatchProgress("mc", where=f" on {cluster}" if cluster else "")
            if progress is True
            else None,
            ci_width=ci_width,
            max_seeds=max_seeds,
            on_seed=on_seed if callable(progress) else None,
        )
    except BatchInterrupted as stop:  # the seeds done are written, then exit 130
        if stop.partial:
            done_seeds, done_rows = zip(*stop.partial, strict=True)
            write_mc(out_dir, cfg, list(done_seeds), list(done_rows))
        end_batch(out_dir, seeds, "seed", stop, len(stop.partial or ()))
        raise
    doc = finish_batch(
        out_dir,
        outcome.total,
        "seed",
        lambda: write_mc(out_dir, cfg, seed_list, rows, outcome.ci_facts()),
        runs_run=outcome.ran,
        runs_skipped=outcome.skipped,
        **outcome.backend,
    )
    with after_the_results(out_dir, "figures" if figures else "printing"):
        _print_mc(doc, out_dir, figures, json_out, len(seed_list), t0)
    return EXIT_OK


def _print_mc(
    doc: dict[str, Any], out_dir: Path, figures: bool, json_out: bool, seeds: int, t0: float
) -> None:
    """``covnet mc``'s figure (with ``figures``) and printout of a mobile batch's
    ``montecarlo.json`` document ``doc`` (``seeds`` seeds, begun at ``perf_counter()``
    ``t0``)."""
    figure = None
    if figures:
        from covnet.mobile.plots import mc_figure  # matplotlib: start-up of the other commands

        figure = mc_figure(out_dir)
    agg = doc["aggregate"]
    if json_out:  # stdout holds JSON only: a row per target, then the overall one
        for tid, b in [*agg["targets"].items(), ("overall", agg["overall"])]:
            print(json.dumps({"target": tid, "seeds": seeds, **b}))
        print(f"results: {out_dir / MC_FILE}", file=sys.stderr)
        return
    print(
        f"Monte Carlo: {out_dir / MC_FILE}  (config {doc['config_hash']}, seeds "
        f"0..{seeds - 1}, {time.perf_counter() - t0:.1f} s)"
    )
    print(
        f"  {'target':>8} {'RMSE m':>18} {'2nd half':>18} {'missed':>8} {'2nd half':>9}"
        f"  (means over seeds ± 95 % half-width; {CUT})"
    )
    for tid, b in [*agg["targets"].items(), ("overall", agg["overall"])]:
        print(
            f"  {tid:>8} {_pm(b['rmse_position_m']):>18} "
            f"{_pm(b['rmse_position_second_half_m']):>18} "
            f"{_pct(b['missed_detection_rate']['mean']):>8} "
            f"{_pct(b['missed_detection_rate_second_half']['mean']):>9}"
        )
    print(
        f"  usage cost {agg['usage_cost_total']['mean']:.1f}, platform travel "
        f"{agg['platform_travel_m']['total']['mean']:.0f} m (means)"
    )
    opt = agg.get("optimality")
    if opt is not None and not opt["decisions"]:
        print(_none_solved_text(opt))
    elif opt is not None:
        print(
            f"  optimality: LP + post-step worse than the MILP in "
            f"{opt['decisions_lp_post_worse']}/{opt['decisions']} decisions "
            f"({_pct(opt['share_lp_post_worse'])}), mean gap {100 * opt['mean_gap']:.4f} %, "
            f"max gap {100 * opt['max_gap']:.2f} %, {opt['conflicts_resolved']} conflicts resolved"
            + _not_optimal_text(opt)
        )
    if figure is not None:
        print(f"figure: {figure}")


def bench(args: Any, cfg: Any = None) -> int:
    """``covnet bench mobile [--json]``."""
    return bench_run(args.json)


def bench_run(
    json_out: bool,
    *,
    milp: bool = True,
    problems: int = 3,
    repeat: int = 7,
) -> int:
    """``covnet bench mobile [--json]``: one decision's cost tensor and solvers over
    N ∈ {4, 10, 25, 50} × M ∈ {3, 10, 30, 100}, capacity none and ⌈1.5 M/N⌉ (medians, ms)."""
    from covnet.mobile import bench  # start-up time of the other commands

    def progress(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    rows = bench.run(
        problems=problems, repeat=repeat, milp=milp, progress=None if json_out else progress
    )
    goals = bench.goals(rows)
    if json_out:
        for row in rows:
            print(json.dumps(row))
        print(json.dumps({"goals": goals}))
        return EXIT_OK

    def ms(v: float | None) -> str:
        return "-" if v is None else f"{v:.3f}"

    print(
        f"{'N':>3} {'M':>4} {'cap':>4} {'cost':>8} {'lp':>8} {'decision':>9} {'closed':>8} "
        f"{'highs-ds':>9} {'milp':>9} {'worse':>6}   (medians, ms)"
    )
    for r in rows:
        cap = "-" if r["capacity"] is None else str(r["capacity"])
        worse = f"{r['lp_post_worse']}/{r['problems']}" if "lp_post_worse" in r else "-"
        print(
            f"{r['N']:>3} {r['M']:>4} {cap:>4} {ms(r['cost_ms']):>8} {ms(r['lp_ms']):>8} "
            f"{ms(r['decision_ms']):>9} {ms(r['closed_form_ms']):>8} {ms(r['lp_highs_ms']):>9} "
            f"{ms(r['milp_ms']):>9} {worse:>6}"
        )
    size = goals.get("size", "?")
    if "decision_with_capacity_ms" in goals:
        ok = "met" if goals["decision_goal_met"] else "NOT met"
        print(
            f"goal: whole decision (cost tensor + LP, capacity) at {size}: "
            f"{goals['decision_with_capacity_ms']:.2f} ms < {bench.GOAL_DECISION_MS:.0f} ms: {ok}"
        )
    if "closed_form_ms" in goals:
        ok = "met" if goals["closed_form_goal_met"] else "NOT met"
        print(
            f"goal: closed form at {size}: {goals['closed_form_ms']:.3f} ms "
            f"< {bench.GOAL_CLOSED_FORM_MS:.0f} ms: {ok} (with the cost tensor: "
            f"{goals['decision_no_capacity_ms']:.2f} ms)"
        )
    return EXIT_OK


def plot(run_dir: Path) -> list[Path]:
    """``covnet plot`` of a mobile run directory (its figure) or Monte Carlo directory (the
    means over seeds with their 95 % intervals)."""
    # matplotlib: start-up of the other commands
    from covnet.mobile.plots import make_figure, mc_figure

    if (run_dir / MC_FILE).is_file():
        return [mc_figure(run_dir)]
    missing = [f for f in ("summary.json", "arrays.npz") if not (run_dir / f).is_file()]
    if missing:
        raise UsageError(
            f"{run_dir}: not a complete mobile run directory (missing {', '.join(missing)}) "
            f"nor a Monte Carlo one ({MC_FILE})"
        )
    return [make_figure(run_dir)]


def _not_optimal_text(opt: dict[str, Any]) -> str:
    """The decisions the optimality figures leave out: the MILP proved no optimum in time."""
    n = opt.get("exact_not_optimal", 0)
    return f" ({n} more left out: the MILP proved no optimum within its time limit)" if n else ""
