"""The passive kind's commands (registered by :mod:`covnet.passive.kind`):

* :func:`mc`: ``covnet mc configs/passive.yaml [--trials N] [--out DIR]``: the §9 protocol;
  writes ``results.json``, ``results.md``, ``config.json``, ``fig_p_vs_d.png``,
  ``fig_time.png``;
* :func:`bench`: ``covnet bench passive [--json]``: median time per scan per method;
* :func:`run`: ``covnet run configs/passive.yaml``: one scan associated with the configured
  method; writes ``association.json``, ``config.json``, ``run.json`` and ``scene.png``;
* :func:`after_up`: after ``covnet up configs/passive.yaml``: the summary and the scene figure.

Each returns an exit status (0 success); a user's mistake raises
:class:`~covnet.errors.UsageError`.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from covnet import __version__
from covnet.batches.pool import BatchInterrupted, end_batch, finish_batch
from covnet.batches.trials import BatchProgress, batch_options, prepare_batch_out, write_batch_info
from covnet.errors import UsageError
from covnet.passive.associate import header, scan_record
from covnet.passive.config import PassiveConfig, normalised
from covnet.passive.montecarlo import (
    run_grid_outcome,
    trial_key,
    trials_text,
    where_it_ran,
    write_results,
)
from covnet.passive.scene import draw
from covnet.runs.rundir import RUN_INFO, after_the_results, read_json, utc_now, write_json

__all__ = ["after_up", "bench", "mc", "run"]

EXIT_OK = 0


def mc(args: Any, cfg: PassiveConfig) -> int:
    """``covnet mc configs/passive.yaml [--trials N] [--out DIR] [--force] [--workers W]
    [--cluster ADDRESS] [--ci-width X [--max-seeds N]]``."""
    n = args.trials if args.trials is not None else cfg.montecarlo.trials
    opts = batch_options(args, n)
    return mc_run(
        cfg,
        args.out,
        args.trials,
        force=args.force,
        workers=opts.workers,
        cluster=opts.cluster,
        ci_width=opts.ci_width,
        max_seeds=opts.max_seeds,
        figures=not getattr(args, "no_figures", False),
        json_out=getattr(args, "json", False),
    )


def mc_run(
    cfg: PassiveConfig,
    out: str | Path | None = None,
    trials: int | None = None,
    progress: bool | Callable[[int, int, str], None] = True,
    *,
    force: bool = False,
    workers: int | None = None,
    cluster: str | None = None,
    ci_width: float | None = None,
    max_seeds: int | None = None,
    figures: bool = True,
    json_out: bool = False,
) -> int:
    """Run the Monte Carlo protocol of the config's ``montecarlo`` grid (``trials`` overrides
    ``montecarlo.trials``) and write the results and figures to ``out``; every cell's trials
    are written to ``OUT/trials`` as they finish (the same command resumes).  ``progress``:
    ``True`` one live progress line on stderr, ``False`` nothing, or a callable ``(cells
    done, cells, label)``."""
    from covnet.passive.plots import mc_figures  # matplotlib: start-up of the other commands

    if trials is not None and not (isinstance(trials, int) and trials >= 1):
        raise UsageError(f"--trials: must be an integer >= 1, got {trials}")
    key = trial_key(cfg)
    out_dir, _ = prepare_batch_out(out, f"{cfg.name}-mc", force, "mc", key)
    write_batch_info(out_dir, "mc", key, {})
    cb = progress if callable(progress) else None
    n = trials or cfg.montecarlo.trials
    cells = (
        len(cfg.montecarlo.formations)
        * len(cfg.montecarlo.spacings_km)
        * len(cfg.montecarlo.sigmas_mrad)
        * len(cfg.montecarlo.clutter)
    )
    print(
        f"monte carlo: {cells} cells x {n} trials, methods {', '.join(cfg.montecarlo.methods)}",
        file=sys.stderr if json_out else sys.stdout,  # --json: stdout holds JSON only
        flush=True,
    )
    line = (
        BatchProgress("mc", where=f" on {cluster}" if cluster else "") if progress is True else None
    )
    try:
        rows, facts, outcome = run_grid_outcome(
            cfg,
            trials=trials,
            workers=workers,
            progress=cb,
            out=out_dir,
            cluster=cluster,
            batch_progress=line,
            ci_width=ci_width,
            max_seeds=max_seeds,
        )
    except BatchInterrupted as stop:  # the cells done are written, then exit 130
        kept = len(stop.partial[0]) // len(cfg.montecarlo.methods) if stop.partial else 0
        if kept:
            write_results(out_dir, cfg, *stop.partial)
        end_batch(out_dir, cells * n, "cell", stop, kept)
        raise
    doc = finish_batch(
        out_dir,
        outcome.total,
        "cell",
        lambda: write_results(out_dir, cfg, rows, facts),
        runs_run=outcome.ran,
        runs_skipped=outcome.skipped,
        **outcome.backend,
    )
    with after_the_results(out_dir, "figures" if figures else "printing"):
        figs = mc_figures(out_dir) if figures else []
        if json_out:  # stdout holds JSON only: a row per cell and method
            for row in doc["rows"]:
                print(json.dumps(row))
            print(f"results: {out_dir / 'results.json'}", file=sys.stderr)
            return EXIT_OK
        _print_mc_summary(doc)
        print(f"results: {out_dir / 'results.json'}, {out_dir / 'results.md'}")
        for f in figs:
            print(f"figure: {f}")
    return EXIT_OK


def _print_mc_summary(doc: dict[str, Any]) -> None:
    rows = doc["rows"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cot_t = [r["median_time_s"] for r in rows if r["method"] == "cot"]
    print(
        f"{doc['cells']} cells x {trials_text(doc)} trials in {doc['wall_s']:.1f} s "
        f"on {where_it_ran(doc) if doc.get('cluster') else str(doc['workers']) + ' processes'} "
        f"(config {doc['config_hash']}, seed {doc['seed']})"
    )
    print(f"{'method':>8} {'mean p':>7} {'worst p':>8}  {'worst cell':<44} {'median ms':>9}")
    for m in methods:
        rs = [r for r in rows if r["method"] == m]
        ps = [r["p"] for r in rs if r["p"] is not None]
        worst = min(rs, key=lambda r: 2.0 if r["p"] is None else r["p"])
        cell = (
            f"{worst['formation']} d={worst['d_km']:g} σ={worst['sigma_mrad']:g} "
            f"clutter {'on' if worst['clutter'] else 'off'}"
        )
        t = float(np.median([r["median_time_s"] for r in rs]))
        ratio = f"  ({t / float(np.median(cot_t)):.1f}x cot)" if cot_t and m != "cot" else ""
        print(f"{m:>8} {np.mean(ps):>7.3f} {worst['p']:>8.3f}  {cell:<44} {1e3 * t:>9.3f}{ratio}")


def bench(args: Any, cfg: Any = None) -> int:
    """``covnet bench passive [--json]``."""
    return bench_run(args.json)


def bench_run(json_out: bool = False) -> int:
    """Benchmark every registered method on the spec's scenes; print a table (or JSON rows)."""
    from covnet.passive.bench import GOAL_RATIO, SPACINGS, run  # start-up of the others

    res = run(progress=None if json_out else (lambda m: print(m, file=sys.stderr, flush=True)))
    rows, summ = res["rows"], res["summary"]
    if json_out:
        for r in rows:
            print(json.dumps(r))
        print(json.dumps({"summary": summ}))
        return EXIT_OK
    methods = list(dict.fromkeys(r["method"] for r in rows))
    print(
        f"passive association: {summ['scenes']} scenes x {summ['scans_per_scene']} scans "
        f"(2 formations, d 0.5/1/2 km, sigma 1/3 mrad, clutter off/on); {summ['machine']}"
    )
    head = "".join(f" {f'd={d:g} ms':>9}" for d in SPACINGS)
    print(
        f"{'method':>8}{head} {'all ms':>8} {'vs cot':>7} "
        + "".join(f" {f'p d={d:g}':>8}" for d in SPACINGS)
    )

    def row(m: str, d: float | None) -> dict[str, Any]:
        return next(r for r in rows if r["method"] == m and r["d_km"] == d and r["clutter"] is None)

    cot_all = row("cot", None)["median_s"] if "cot" in methods else None
    for m in methods:
        per_d = [row(m, d) for d in SPACINGS]
        allr = row(m, None)
        vs = f"{allr['median_s'] / cot_all:>6.1f}x" if cot_all and m != "cot" else f"{'':>7}"
        print(
            f"{m:>8}"
            + "".join(f" {1e3 * r['median_s']:>9.3f}" for r in per_d)
            + f" {1e3 * allr['median_s']:>8.3f} {vs} "
            + "".join(f" {r['p']:>8.3f}" for r in per_d)
        )
    if "ratio_lr_over_cot_d_ge_1" in summ:
        r = summ["ratio_lr_over_cot_d_ge_1"]
        acc = summ["p_d_ge_1"]
        verdict = "met" if summ["speed_goal_met"] else "NOT met"
        print(
            f"goal (cot >= {GOAL_RATIO:g}x faster than lr for d >= 1 km): "
            f"lr/cot = {r:.1f}x, {verdict}"
        )

        def pair(key: str) -> str:
            return f"{acc[key]['cot']:.3f}/{acc[key]['lr']:.3f}"

        print(
            f"  accuracy there, p cot/lr: clean {pair('clean')} "
            f"(horizontal {pair('clean horizontal')}, cross {pair('clean cross')}); "
            f"clutter {pair('clutter')} (horizontal {pair('clutter horizontal')}, "
            f"cross {pair('clutter cross')})"
        )
        print(
            "  (the cot method's clean ceiling ~0.986 is structural: its two 3-sigma tests reject "
            "~1.4 % of true triples, spec §10)"
        )
    return EXIT_OK


def run(cfg: PassiveConfig, out_dir: Path, *, figures: bool = True) -> int:
    """Draw one scan of the config's scene, associate it with ``association.method``,
    triangulate the triples; write ``association.json`` (what config and seed determine),
    ``config.json``, ``run.json`` (the association's wall time) and ``scene.png``.  (This scan
    is scan 1 of ``covnet up`` with the same seed: trial 0.)"""
    seed = cfg.seed
    model = cfg.scene_model()
    params = cfg.assoc_params(model)
    scene = draw(model, seed, 0)
    method = cfg.association.method
    rec, positions, _ = scan_record(scene.scan, params, method, scene)
    dt = rec.pop("time_s")
    doc = {"kind": "passive-scene", **header(cfg, seed, method), "trial": 0, **rec}
    Z = rec["triples"]
    correct = rec["correct"]
    hit, n_truth, n_out = (rec["score"][k] for k in ("correct", "truth", "output"))
    a_status, a_message = rec["status"], rec["message"]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "config.json", normalised(cfg))
    write_json(out_dir / "association.json", doc)
    write_json(
        out_dir / RUN_INFO,
        {
            "created_utc": utc_now(),
            "covnet_version": __version__,
            "mode": "in-process",
            "kind": "passive",
            "association_time_s": dt,
        },
    )
    print(
        f"{method}: {hit}/{n_truth} targets associated correctly, {n_out - hit} wrong triple(s), "
        f"{1e3 * dt:.2f} ms (status {a_status}: {a_message})"
    )
    for t, p, ok in zip(Z, positions, correct, strict=True):
        tag = "correct" if ok else "GHOST"
        print(f"  triple {t}: ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) km  {tag}")
    print(f"run directory: {out_dir}  (config {doc['config_hash']}, seed {seed})")
    if figures:
        from covnet.passive.plots import scene_figure  # matplotlib: start-up of the others

        print(f"figure: {scene_figure(out_dir)}")
    return EXIT_OK


def after_up(cfg: PassiveConfig, out: Path, *, figures: bool) -> None:
    """The summary of a passive network run, and its scene figure (the last associated scan)."""
    path = out / "association.json"
    if not path.is_file():
        return
    doc = read_json(path)
    sm = doc["summary"]
    print(
        f"{doc['method']}: {sm['scans']} scan(s), {sm['associated']} associated, "
        f"{sm['unassociated']} not associated (a list missing); "
        f"{sm['correct']}/{sm['truth']} targets associated correctly, "
        f"{sm['output'] - sm['correct']} wrong triple(s)"
    )
    if figures and "correct" in doc:  # a scored scan (the manager redraws the truth)
        from covnet.passive.plots import scene_figure  # matplotlib: start-up

        print(f"figure: {scene_figure(out)}")
    print(f"run directory: {out}  (config {doc['config_hash']}, seed {doc['seed']})")


def plot(run_dir: Path) -> list[Path]:
    """``covnet plot`` of a passive run directory (its scene figure) or Monte Carlo directory
    (its two figures)."""
    # matplotlib: start-up of the other commands
    from covnet.passive.plots import mc_figures, scene_figure

    if (run_dir / "results.json").is_file():
        return mc_figures(run_dir)
    if not (run_dir / "association.json").is_file():
        raise UsageError(
            f"{run_dir}: not a complete passive run directory (missing association.json) nor "
            "a Monte Carlo one (results.json)"
        )
    doc = read_json(run_dir / "association.json")
    if "correct" not in doc:
        raise UsageError(
            f"{run_dir}: no scan of this run was associated (association.json has none): "
            "there is no scene to draw"
        )
    return [scene_figure(run_dir)]
