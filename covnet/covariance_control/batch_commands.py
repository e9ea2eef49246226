"""The covariance-control kind's batch commands, ``covnet mc``, ``compare`` and ``sweep``: many
seeded runs (worker processes or a Dask cluster, :mod:`covnet.batches.trials`), their tables with 95
%
intervals, curves and figures.  Apart from :mod:`covnet.covariance_control.commands` so that
``covnet run`` does not import the batch machinery (start-up time).

Each returns an exit status (0 success); a user's mistake raises
:class:`~covnet.errors.UsageError`; an interruption writes the complete rows and goes on (exit 130).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from covnet.batches.pool import BatchInterrupted, end_batch, finish_batch, write_rows
from covnet.batches.trials import BatchProgress, batch_options, prepare_batch_out, write_batch_info
from covnet.covariance_control.commands import CURVES, EXIT_OK, metric_opt
from covnet.covariance_control.config import Scenario, SweepSpec, from_dict, normalised
from covnet.errors import UsageError
from covnet.runs.rundir import CONFIG, after_the_results, write_json, write_npz


def _batch_out(args: argparse.Namespace, name: str, command: str, key: str) -> Path:
    """The batch's directory (a new one, or its own to resume) with ``batch.json`` in it."""
    out, _ = prepare_batch_out(args.out, name, args.force, command, key)
    write_batch_info(out, command, key, {})
    return out


def compare(args: argparse.Namespace, sc: Scenario) -> int:
    """``covnet compare``: the fusion structures side by side over a Monte Carlo batch."""
    from covnet.covariance_control import compare as cmp  # scipy.stats: start-up of the rest

    if getattr(args, "policies", None) is not None:
        return compare_policies(args, sc)
    if getattr(args, "budget", None) is not None:
        raise UsageError("--budget: the policies' budget; give it with --policies")
    if sc.surveillance is not None:
        raise UsageError(
            "compare: the fusion structures are compared on the one-target scenario; "
            "surveillance fuses returns centrally only (covnet mc evaluates it; covnet compare "
            "--policies compares allocation policies on it)"
        )
    if sc.multitarget:
        raise UsageError(
            "compare: the fusion structures are compared on the one-target scenario; with "
            "'targets:' run covnet mc --fusion central and covnet mc --fusion info"
        )
    given = args.modes if args.modes is not None else ",".join(cmp.default_modes())
    modes = [m.strip() for m in given.split(",") if m.strip()]
    for m in modes:
        if m not in cmp.modes():
            raise UsageError(f"--modes: unknown mode {m!r}; choose from {', '.join(cmp.modes())}")
    if not modes:
        raise UsageError("--modes: name at least one mode")
    dup = sorted({m for m in modes if modes.count(m) > 1})  # as --policies
    if dup:
        raise UsageError(f"--modes: {', '.join(dup)} named twice")
    metric = metric_opt(sc, args.metric, sc.allocation.metrics[0])
    if args.runs < 2:
        raise UsageError(f"--runs: at least 2 runs for a NEES band, got {args.runs}")
    if args.graph is not None and not any(m.startswith("peer-") for m in modes):
        raise UsageError(
            f"--graph {args.graph}: the peer modes' graph, and none of {', '.join(modes)} is "
            "one (peer-info, peer-ci)"
        )
    for m in modes:  # each mode's config is valid (a custom graph has edges) before any file
        cmp.scenario_for(sc, m, args.graph)
    opts = batch_options(args, args.runs)
    key = cmp.trial_key(sc, metric, args.graph)
    out = _batch_out(args, f"{sc.name}-compare", "compare", key)
    total = len(modes) * args.runs
    print(
        f"comparing {', '.join(modes)} on {sc.name}: metric {metric}, {args.runs} seeds from "
        f"{sc.seed}, {total} runs",
        file=sys.stderr,
        flush=True,
    )
    meta = {
        "scenario": sc.name,
        "metric": metric,
        "runs": args.runs,
        "first_seed": sc.seed,
        "graph": args.graph or sc.fusion.peer.graph,
    }
    title = cmp.figure_title(meta)

    def work() -> Any:
        return cmp.compare_outcome(
            sc,
            modes,
            metric,
            args.runs,
            graph=args.graph,
            progress=BatchProgress("compare", where=opts.where),
            out=out,
            **_trial_options(opts),
        )

    return _batch_results(cmp, args, sc, out, work, total, "mode", meta, title, key)


def compare_policies(args: argparse.Namespace, sc: Scenario) -> int:
    """``covnet compare --policies``: allocation policies side by side over paired seeds
    (:mod:`covnet.covariance_control.compare_policies`), one target or ``targets:``."""
    from covnet.covariance_control import compare_policies as cp  # start-up of the rest

    policies = cp.parse_policies(args.policies)
    budget = cp.parse_budget(args.budget)
    if args.graph is not None:
        raise UsageError(
            "--graph: the peer modes' graph; --policies run the config's fusion centre"
        )
    for opt, val in (("--ci-width", args.ci_width), ("--max-seeds", args.max_seeds)):
        if val is not None:  # the policies share their seeds (paired): no per-point seed counts
            raise UsageError(
                f"{opt}: --policies compares every policy on the same --runs seeds (paired); "
                "give --runs instead"
            )
    metric = metric_opt(sc, args.metric, sc.allocation.metrics[0])
    if args.runs < 2:
        raise UsageError(f"--runs: at least 2 runs for the 95 % intervals, got {args.runs}")
    opts = batch_options(args, args.runs)
    cp.check(sc, policies, budget)  # every refusal before a directory is made
    if sc.surveillance is not None:
        return _surveillance_policies(args, sc, policies, budget, opts)
    key = cp.trial_key(sc, metric)
    out = _batch_out(args, f"{sc.name}-compare-policies", "compare", key)
    extra = 1 if budget == cp.MATCH and cp.REFERENCE not in policies else 0
    total = (len(policies) + extra) * args.runs
    print(
        f"comparing policies {', '.join(policies)} on {sc.name}: metric {metric}, {args.runs} "
        f"seeds from {sc.seed} (the same for each)"
        + (", budget matched to covariance control's sensors per scan" if budget == cp.MATCH
           else f", budget K = {budget}" if budget is not None else ""),
        file=sys.stderr,
        flush=True,
    )  # fmt: skip
    plan: list[Any] = []

    def work() -> Any:
        rows, outcome, p = cp.compare_outcome(
            sc,
            policies,
            metric,
            args.runs,
            budget=budget,
            workers=opts.workers,
            cluster=opts.cluster,
            progress=BatchProgress("compare", where=opts.where),
            out=out,
        )
        plan.append(p)
        return rows, outcome

    meta: dict[str, Any] = {
        "scenario": sc.name,
        "compared": "policies",
        "policies": policies,
        "metric": metric,
        "runs": args.runs,
        "first_seed": sc.seed,
        "budget": budget,
        "fusion": sc.fusion.mode,
    }
    title = cp.figure_title(meta)

    def budgets() -> dict[str, Any]:
        if not plan:  # interrupted before the budgets were known
            return {}
        return {"budgets": plan[0].budgets, "budget_match": plan[0].matched}

    return _batch_results(
        cp, args, sc, out, work, total, "policy", meta, title, key, more_meta=budgets
    )


def _surveillance_metrics(args: argparse.Namespace, sc: Scenario) -> Scenario:
    """``sc`` with only ``--metric``'s metric when one is given (a surveillance batch runs every
    metric of the config otherwise): it ran them all, or the config's, whatever was asked."""
    if getattr(args, "metric", None) is None:
        return sc
    metric = metric_opt(sc, args.metric, sc.allocation.metrics[0])
    data = normalised(sc)
    data["allocation"] = {**data["allocation"], "metrics": [metric]}
    return from_dict(data, sc.name)


def _surveillance_policies(
    args: argparse.Namespace, sc: Scenario, policies: list[str], budget: Any, opts: Any
) -> int:
    """``covnet compare --policies`` of a surveillance config
    (:func:`covnet.covariance_control.surveillance_batch.policy_compare`): ``compare.json`` /
    ``.csv`` and the table."""
    # start-up: the surveillance batch only for configs with surveillance
    from covnet.covariance_control import compare_policies as cp
    from covnet.covariance_control import surveillance_batch as sb

    if not isinstance(budget, int) and budget is not None:
        raise UsageError("--budget match: not with a surveillance config; give --budget K")
    if opts.cluster is not None:
        raise UsageError("--cluster: a surveillance comparison runs on this machine's cores")
    sc = _surveillance_metrics(args, sc)
    metrics = list(sc.allocation.metrics)
    # the config's hash keys the batch (its name did: a changed config with the same name ran
    # into, and overwrote, the earlier batch's directory without --force)
    key = cp.trial_key(sc, ",".join(metrics))
    out = _batch_out(args, f"{sc.name}-compare-policies", "compare", key)
    print(
        f"comparing policies {', '.join(policies)} on {sc.name}: metrics {', '.join(metrics)}, "
        f"{args.runs} seeds from {sc.seed} (the same for each)"
        + (f", budget K = {budget}" if budget else ""),
        file=sys.stderr,
        flush=True,
    )
    t0 = time.perf_counter()
    try:
        rows, outcome = sb.policy_compare(
            sc, policies, budget, args.runs, out=out, workers=opts.workers,
            progress=BatchProgress("compare"),
        )  # fmt: skip
    except BatchInterrupted as stop:  # run.json says so, and that the same command resumes
        end_batch(out, stop.total, "policy", stop)
        raise
    meta = {
        "scenario": sc.name,
        "compared": "policies",
        "policies": policies,
        "runs": args.runs,
        "first_seed": sc.seed,
        "budget": budget,
        "surveillance": True,
        "metric": ",".join(metrics),
        "trial_hash": key,
    }
    return _surveillance_rows(
        args, sc, out, "compare", rows, outcome, meta, lambda r: {"policy": r["point"]},
        lambda: sb.compare_table(rows), t0, lambda: sb.compare_figure(out, rows),
    )  # fmt: skip


def _surveillance_rows(
    args: argparse.Namespace, sc: Scenario, out: Path, stem: str, rows: list[dict[str, Any]],
    outcome: Any, meta: dict[str, Any], lead: Callable[[dict[str, Any]], dict[str, Any]],
    table: Callable[[], str], t0: float, figure: Callable[[], Path],
) -> int:  # fmt: skip
    """A surveillance sweep's or comparison's files and printout: ``<stem>.json`` (every row
    in full, each scalar's interval) and ``<stem>.csv`` (``lead(row)``, then each scalar's mean
    and interval), the config, ``run.json``'s status (:func:`finish_batch`: last); then the
    figure (``figure()``, unless ``--no-figures``) and the table, or with ``--json`` the rows
    (:func:`after_the_results`: an interruption there keeps the results and says so)."""
    # start-up: the surveillance batch only for configs with surveillance
    from covnet.covariance_control import surveillance_batch as sb

    flat = [
        {**lead(r), "metric": r["metric"], "seeds": r["seeds"],
         **{f"{k}_mean": r[k]["mean"] for k in sb.SCALARS},
         **{f"{k}_ci95": r[k]["ci95"] for k in sb.SCALARS}}
        for r in rows
    ]  # fmt: skip
    if any(r.get("vs_reference") for r in rows):  # a policy comparison's paired differences
        for r, f in zip(rows, flat, strict=True):
            f["vs_reference"] = r.get("vs_reference")
            for k in sb.SCALARS:
                d = r.get(f"{k}_vs_reference") or {}
                f[f"{k}_vs_reference_mean"] = d.get("mean")
                f[f"{k}_vs_reference_ci95"] = d.get("ci95")

    def write() -> None:
        write_rows(out, stem, [{**r, **f} for r, f in zip(rows, flat, strict=True)], meta,
                   list(flat[0]))  # fmt: skip
        write_json(out / CONFIG, normalised(sc))

    finish_batch(out, outcome.total, "seed", write, runs_run=outcome.ran,
                 runs_skipped=outcome.skipped, wall_s=outcome.wall_s,
                 **outcome.backend)  # fmt: skip
    with after_the_results(out, "printing" if args.no_figures else "figures"):
        drawn = None if args.no_figures else figure()
        if getattr(args, "json", False):  # stdout holds JSON only
            for r in rows:
                print(json.dumps(r))
            print(f"results: {out / f'{stem}.json'}", file=sys.stderr)
            return EXIT_OK
        print(table())
        print(f"results: {out / f'{stem}.json'}  ({time.perf_counter() - t0:.1f} s)")
        if drawn is not None:
            print(f"figure: {drawn}")
    return EXIT_OK


def _trial_options(opts: Any) -> dict[str, Any]:
    return {
        "workers": opts.workers,
        "cluster": opts.cluster,
        "ci_width": opts.ci_width,
        "max_seeds": opts.max_seeds,
    }


def _batch_results(
    module: Any,
    args: argparse.Namespace,
    sc: Scenario,
    out: Path,
    work: Callable[[], Any],
    total: int,
    what: str,
    meta: Any,
    title: str,
    key: str,
    more_meta: Callable[[], dict[str, Any]] | None = None,
) -> int:
    """Run ``covnet compare`` / ``sweep``'s ``work`` (its table's rows and the trials'
    :class:`~covnet.batches.trials.Outcome`, from ``total`` runs) and write: the table files, the
    per-scan curves (``curves.npz``), the config (which says the directory's kind, for ``covnet
    plot``), ``run.json``'s status (last: :func:`finish_batch`), the figures, the printout.
    Interrupted: the complete rows (each a ``what``) are written, no figure, and the
    interruption goes on (exit 130); the trials stay in ``out/trials`` for the same command to
    resume.  Interrupted while drawing or printing: ``run.json`` stays ``completed`` and says
    so (:func:`after_the_results`).  ``more_meta()``: what the
    work found out that the table's meta data should say (``--budget match``'s K)."""
    meta = {
        **meta,
        "burn_in_scans": sc.evaluation.burn_in_scans,
        "trial_hash": key,
    }
    try:
        rows, outcome = work()
    except BatchInterrupted as stop:
        if stop.partial:
            meta = {**meta, **(more_meta() if more_meta else {})}
            module.write_table(out, stop.partial, meta)
            write_json(out / CONFIG, normalised(sc))
        end_batch(out, total, what, stop, len(stop.partial or ()))
        raise
    meta = {**meta, **outcome.ci_facts(), **(more_meta() if more_meta else {})}

    def write() -> dict[str, Any]:
        module.write_table(out, rows, meta)
        curves: dict[str, Any] = module.curves(outcome.results)
        write_npz(out / CURVES, curves)
        write_json(out / CONFIG, normalised(sc))
        return curves

    curves = finish_batch(
        out,
        outcome.total,
        what,
        write,
        runs_run=outcome.ran,
        runs_skipped=outcome.skipped,
        wall_s=outcome.wall_s,
        trials_per_s=outcome.ran / outcome.wall_s if outcome.wall_s > 0 else None,
        **outcome.backend,
    )
    with after_the_results(out, "printing" if args.no_figures else "figures"):
        if not args.no_figures:
            module.make_figure(out, rows, title)
            module.curves_figure(out, curves, module.default_curves(rows))
        if args.json:  # stdout holds JSON only
            for r in rows:
                print(json.dumps(r))
            print(f"results: {out}", file=sys.stderr)
        else:
            print(module.format_table(rows))
            print(f"results: {out}")
    return EXIT_OK


def sweep(args: argparse.Namespace, sc: Scenario) -> int:
    """``covnet sweep``: the latency grid of the config's ``sweep`` section."""
    from covnet.covariance_control import sweep as sw  # start-up time of the other commands

    if sc.surveillance is not None:
        return _surveillance_sweep(args, sc)
    if sc.multitarget:
        raise UsageError(
            "sweep: the latency grid runs the one-target scenario; with 'targets:' give "
            "network.latency in the config and use covnet run or covnet mc"
        )
    if not sc.fusion.has_centre:
        raise UsageError("sweep: fusion.mode peer has no fusion centre; sweep the centre modes")
    spec = sc.sweep or SweepSpec()
    metric = metric_opt(sc, args.metric, spec.metric or sc.allocation.metrics[0])
    if args.seeds is not None and args.seeds < 1:
        raise UsageError(f"--seeds: must be >= 1, got {args.seeds}")
    seeds = args.seeds or spec.seeds
    opts = batch_options(args, seeds)
    points = sw.grid(spec)
    why = sw.refused_point(sc, points)  # every point's config before any run or file
    if why is not None:
        raise UsageError(why)
    key = sw.trial_key(sc, metric)
    out = _batch_out(args, f"{sc.name}-sweep", "sweep", key)
    print(
        f"sweeping {sc.name}: {len(points)} grid points x {seeds} seeds = "
        f"{len(points) * seeds} runs, metric {metric}"
        + ("" if sc.sweep else " (no sweep section in the config: the default grid)")
        + (f", seeds added until every 95 % interval is narrower than {opts.ci_width:g} m "
           f"(cap {opts.max_seeds})" if opts.ci_width else ""),
        file=sys.stderr,
        flush=True,
    )  # fmt: skip
    meta = {
        "scenario": sc.name,
        "metric": metric,
        "seeds": seeds,
        "first_seed": sc.seed,
        "delay_kind": spec.delay_kind,
        "deadline_fraction": sc.network.deadline_fraction,
        "period_s": sc.period_s,
    }
    title = sw.figure_title(meta)

    def work() -> Any:
        return sw.sweep_outcome(
            sc,
            metric=metric,
            seeds=seeds,
            progress=BatchProgress("sweep", where=opts.where),
            out=out,
            **_trial_options(opts),
        )

    total = len(points) * seeds
    return _batch_results(sw, args, sc, out, work, total, "grid point", meta, title, key)


def _surveillance_sweep(args: argparse.Namespace, sc: Scenario) -> int:
    """``covnet sweep`` of a surveillance config: the search weight λ over
    ``sweep.search_weight``, each with ``sweep.seeds`` (or ``--seeds``) seeds
    (:mod:`covnet.covariance_control.surveillance_batch`); ``sweep.csv``/``.json``, the table
    and ``sweep.png``."""
    # start-up: the surveillance batch only for configs with surveillance
    from covnet.covariance_control import surveillance_batch as sb
    from covnet.covariance_control import sweep as sw

    spec = sc.sweep
    if spec is None or spec.search_weight is None:
        raise UsageError(
            "sweep: a surveillance config sweeps the search weight: give "
            "sweep: {search_weight: [0, 5, 20, 50], seeds: 8}"
        )
    for opt in ("cluster", "ci_width"):
        if getattr(args, opt, None) is not None:
            raise UsageError(f"--{opt.replace('_', '-')}: not for a surveillance sweep")
    if args.seeds is not None and args.seeds < 1:
        raise UsageError(f"--seeds: must be >= 1, got {args.seeds}")
    seeds = args.seeds or spec.seeds
    batch_options(args, seeds)  # --workers, --max-seeds: checked as for every batch
    sc = _surveillance_metrics(args, sc)
    # the config's hash keys the batch (its name did: a changed config with the same name ran
    # into, and overwrote, the earlier batch's directory without --force)
    key = sw.trial_key(sc, ",".join(sc.allocation.metrics))
    out = _batch_out(args, f"{sc.name}-sweep", "sweep", key)
    weights = list(spec.search_weight)
    print(
        f"sweeping {sc.name}: search weight {weights} x {seeds} seeds = "
        f"{len(weights) * seeds} runs, metrics {', '.join(sc.allocation.metrics)}",
        file=sys.stderr,
        flush=True,
    )
    t0 = time.perf_counter()
    try:
        rows, outcome = sb.weight_sweep(
            sc, weights, seeds, out=out, workers=getattr(args, "workers", None),
            progress=BatchProgress("sweep"),
        )  # fmt: skip
    except BatchInterrupted as stop:  # run.json says so, and that the same command resumes
        end_batch(out, stop.total, "grid point", stop)
        raise
    meta = {
        "scenario": sc.name,
        "seeds": seeds,
        "first_seed": sc.seed,
        "surveillance": True,
        "metric": ",".join(sc.allocation.metrics),
        "trial_hash": key,
    }
    return _surveillance_rows(
        args, sc, out, "sweep", rows, outcome, meta,
        lambda r: {"search_weight": r["search_weight"]}, lambda: sb.sweep_table(rows), t0,
        lambda: sb.sweep_figure(out, rows),
    )  # fmt: skip


def mc(args: argparse.Namespace, sc: Scenario) -> int:
    """``covnet mc CONFIG [--trials N] [--workers W]``: the config over ``N`` seeds from its
    own (default 20), every metric, in parallel worker processes, each seed written to
    ``OUT/trials`` as it finishes (the same command resumes); writes ``montecarlo.json``
    (means with 95 % intervals, every seed's row) and ``montecarlo.png``."""
    from covnet.covariance_control import montecarlo as mcm  # scipy.stats: start-up of the rest

    n = args.trials if args.trials is not None else 20
    if n < 1:
        raise UsageError(f"--trials: must be >= 1, got {n}")
    workers = getattr(args, "workers", None)
    if workers is not None and workers < 1:
        raise UsageError(f"--workers: must be >= 1, got {workers}")
    if not sc.fusion.has_centre:
        raise UsageError("mc: fusion.mode peer is compared by covnet compare, not covnet mc")
    options = (("--cluster", args.cluster), ("--ci-width", args.ci_width),
               ("--max-seeds", args.max_seeds))  # fmt: skip
    for opt, val in options:
        if val is not None:  # no headline metric for --ci-width; the cluster path untried
            raise UsageError(
                f"{opt}: covnet mc of a covariance-control config runs on this "
                "machine's cores only, over --trials seeds"
            )
    batch_options(args, n)  # --workers, and entries registered at run time: as every batch
    key = mcm.trial_key(sc)
    out = _batch_out(args, f"{sc.name}-mc", "mc", key)
    print(
        f"monte carlo: {sc.name}, {n} seeds from {sc.seed}, metrics "
        f"{', '.join(sc.allocation.metrics)}",
        file=sys.stderr,
        flush=True,
    )
    t0 = time.perf_counter()
    try:
        seeds, rows, outcome = mcm.mc_outcome(
            sc, n, out=out, workers=workers, progress=BatchProgress("mc")
        )
    except BatchInterrupted as stop:  # the seeds done are written, then exit 130
        if stop.partial:
            done_seeds, done_rows = zip(*stop.partial, strict=True)
            mcm.write_mc(out, sc, list(done_seeds), list(done_rows))
        end_batch(out, n, "seed", stop, len(stop.partial or ()))
        raise
    doc = finish_batch(
        out,
        outcome.total,
        "seed",
        lambda: mcm.write_mc(out, sc, seeds, rows),
        runs_run=outcome.ran,
        runs_skipped=outcome.skipped,
        wall_s=outcome.wall_s,
        **outcome.backend,
    )
    with after_the_results(out, "printing" if args.no_figures else "figures"):
        figure = None
        if not args.no_figures:
            from covnet.covariance_control.plots import mc_figure  # matplotlib: start-up

            figure = mc_figure(out)
        if args.json:  # stdout holds JSON only
            for row in mcm.json_rows(doc):
                print(json.dumps(row))
            print(f"results: {out / mcm.MC_FILE}", file=sys.stderr)
            return EXIT_OK
        print(mcm.format_table(doc))
        print(f"results: {out / mcm.MC_FILE}  ({time.perf_counter() - t0:.1f} s)")
        if figure is not None:
            print(f"figure: {figure}")
    return EXIT_OK
