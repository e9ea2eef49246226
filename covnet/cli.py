"""The ``covnet`` command line: ``run``, ``check``, ``plot``, ``bench``.

``main(argv) -> int`` so tests call it directly.  Exit status: 0 success, 1 a run failed,
2 a user's mistake (bad config, bad option, an existing run directory), 130 interrupted.
A user's mistake prints one readable message to stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from covnet import __version__

EXIT_OK, EXIT_FAIL, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class UsageError(Exception):
    """A mistake in the user's input, reported without a traceback (exit status 2)."""


def _err(msg: str) -> None:
    print(f"covnet: error: {msg}", file=sys.stderr)


def _load(path: str, seed: int | None = None, fusion: str | None = None):  # type: ignore[no-untyped-def]
    from covnet.config import load, with_run_overrides

    return with_run_overrides(load(path), seed=seed, fusion=fusion)


def _metrics_for(sc, requested: Sequence[str] | None) -> list[str]:  # type: ignore[no-untyped-def]
    from covnet.core.metrics import METRICS

    names = list(requested) if requested else list(sc.allocation.metrics)
    bad = [m for m in names if m not in METRICS]
    if bad:
        raise UsageError(f"--metric: unknown metric {bad[0]!r}; choose from {sorted(METRICS)}")
    return list(dict.fromkeys(names))


def _new_run_dir(name: str) -> Path:
    base = Path("runs") / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"
    out, i = base, 1
    while out.exists():
        i += 1
        out = base.with_name(f"{base.name}-{i}")
    return out


def _prepare_out(out: str | None, name: str, force: bool) -> Path:
    if out is None:
        return _new_run_dir(name)
    p = Path(out)
    if p.exists() and not p.is_dir():
        raise UsageError(f"--out {out}: exists and is not a directory")
    if p.is_dir() and any(p.iterdir()) and not force:
        raise UsageError(
            f"--out {out}: directory is not empty; choose another or pass --force to overwrite"
        )
    return p


def _kind(path: str) -> str:
    from covnet.config import KINDS, scenario_kind

    kind = scenario_kind(path)
    if kind not in KINDS:
        raise UsageError(f"{path}: kind: unknown scenario kind {kind!r}; choose from {list(KINDS)}")
    return kind


def cmd_run(args: argparse.Namespace) -> int:
    kind = _kind(args.config)
    if args.fusion is not None and kind in ("mobile", "passive"):
        raise UsageError("--fusion: only a covariance-control scenario has fusion modes")
    if kind == "mobile":
        from covnet.mobile.cli_entry import run_cmd

        if args.metric:
            raise UsageError("--metric: a mobile scenario has no allocation metric; see --solver")
        return run_cmd(
            args.config,
            args.out,
            args.solver,
            args.seed,
            force=args.force,
            figures=not args.no_figures,
        )
    if kind == "passive":
        from covnet.passive.cli_entry import scene_cmd

        return scene_cmd(args.config, args.out, args.seed)
    if args.solver is not None:
        raise UsageError("--solver: only a mobile scenario (kind: mobile) has solvers")
    from covnet.model import build_model
    from covnet.results import write_run
    from covnet.simulate import shared_trajectory
    from covnet.simulate_decentral import run_mode

    sc = _load(args.config, args.seed, args.fusion)
    metrics = _metrics_for(sc, args.metric)
    out = _prepare_out(args.out, sc.name, args.force)
    model = build_model(sc)
    traj = shared_trajectory(model)
    runs = {}
    node_runs = {}
    latency: dict[str, dict[str, int]] = {}
    slow = not sc.network.latency.is_ideal(sc.sensor_ids)
    if slow and sc.fusion.mode == "peer":
        raise UsageError("network.latency: peer mode has no fusion centre; latency runs need one")
    for m in metrics:
        t0 = time.perf_counter()
        if slow:
            from covnet.latency_sim import run_latency

            runs[m], counts = run_latency(sc, m, model)
            latency[m] = counts.as_dict()
        else:
            runs[m], nodes = run_mode(sc, m, model)
            if nodes is not None:
                node_runs[m] = nodes
        r = runs[m]
        rate = 100.0 * r.enabled.sum() / r.enabled.size
        print(
            f"{m:>10}: {sc.scans} scans in {time.perf_counter() - t0:.2f} s, "
            f"allocation rate {rate:.1f} %"
        )
    summary = write_run(
        out,
        sc,
        traj,
        runs,
        extra={"latency": latency} if latency else None,
        run_info={"mode": "in-process"},
        node_runs=node_runs,
    )
    if not args.no_figures:
        from covnet.plots import make_figures

        make_figures(out)
    _print_summary(out, summary)
    return EXIT_OK


def _print_summary(out: Path, summary: dict) -> None:  # type: ignore[type-arg]
    print(
        f"run directory: {out}  (config {summary['config_hash']}, seed {summary['seed']}, "
        f"fusion {summary.get('fusion', 'central')})"
    )
    for m, blk in summary["metrics"].items():
        peer = summary.get("peer", {}).get(m)
        if peer is not None:
            print(
                f"  {m:>10}: rate {100 * blk['allocation_rate']:5.1f} %, position RMSE "
                f"{peer['rmse_position_mean']:.2f} m (node mean; worst "
                f"{peer['rmse_position_worst']:.2f}), mean NEES {peer['mean_nees']:.2f}, "
                f"nodes agree: {'yes' if peer['agreement'] else 'NO'}"
            )
            continue
        print(
            f"  {m:>10}: rate {100 * blk['allocation_rate']:5.1f} %, "
            f"position RMSE {blk['rmse_position']:.2f} m, mean NEES {blk['mean_nees']:.2f}"
        )


def cmd_mc(args: argparse.Namespace) -> int:
    kind = _kind(args.config)
    if kind == "mobile":
        from covnet.mobile.cli_entry import mc_cmd as mobile_mc

        return mobile_mc(args.config, args.out, args.trials or 20, True, force=args.force)
    if kind == "passive":
        from covnet.passive.cli_entry import mc_cmd as passive_mc

        return passive_mc(args.config, args.out, args.trials, True)
    raise UsageError(
        f"{args.config}: covnet mc runs the mobile and passive evaluation protocols; for a "
        "covariance-control scenario use covnet run (one seed) or covnet up"
    )


def cmd_up(args: argparse.Namespace) -> int:
    from covnet.messages import new_run_id
    from covnet.process import default_run_id
    from covnet.results import load_summary
    from covnet.up import UpError, up

    kind = _kind(args.config)
    mobile = kind == "mobile"
    passive = kind == "passive"
    if passive:
        from covnet.passive.config import load as load_passive
        from covnet.passive.config import with_overrides as passive_overrides

        if args.metric:
            raise UsageError("--metric: a passive scenario has no allocation metric")
        if args.solver is not None:
            raise UsageError("--solver: a passive scenario names its method in association.method")
        if args.seed is not None and args.seed < 0:
            raise UsageError(f"--seed: must be >= 0, got {args.seed}")
        sc = passive_overrides(load_passive(args.config), args.config, seed=args.seed)
        metrics: list[str] = []
    elif mobile:
        from covnet.mobile.config import load as load_mobile
        from covnet.mobile.config import with_overrides as mobile_overrides

        if args.metric:
            raise UsageError("--metric: a mobile scenario has no allocation metric; see --solver")
        sc = load_mobile(args.config)
        sc = mobile_overrides(sc, args.config, seed=args.seed, solver=args.solver)
        metrics = []
    else:
        if args.solver is not None:
            raise UsageError("--solver: only a mobile scenario (kind: mobile) has solvers")
        sc = _load(args.config, args.seed, args.fusion)
        metrics = _metrics_for(sc, args.metric)
    if args.fusion is not None and (mobile or passive):
        raise UsageError("--fusion: only a covariance-control scenario has fusion modes")
    if not (mobile or passive) and not sc.network.latency.is_ideal(sc.sensor_ids):
        if sc.fusion.mode == "peer":
            raise UsageError("network.latency: peer mode has no fusion centre to be late for")
        if not args.realtime and not getattr(args, "netns", False):
            raise UsageError(
                "network.latency describes slow or lossy links: run covnet up with --realtime "
                "(a lockstep run waits for every message), or covnet run / covnet sweep, which "
                "simulate the links in simulated time"
            )
    if args.speed <= 0:
        raise UsageError(f"--speed: must be > 0, got {args.speed}")
    if args.netns:
        from covnet.netns_launch import unsupported_reason

        if args.nodes or args.router:
            raise UsageError(
                "--netns runs the whole network on this machine, each sensor in its own "
                "namespace: not with --nodes or --router (for several hosts, leave out --netns)"
            )
        reason = unsupported_reason()
        if reason is not None:
            raise UsageError(reason)
    out = _prepare_out(args.out, sc.name, args.force)
    nodes = [n.strip() for n in args.nodes.split(",")] if args.nodes else None
    known = {"manager", "world", "recorder", "sensors", *sc.sensor_ids}
    for n in nodes or []:
        if n not in known:
            raise UsageError(f"--nodes: unknown process {n!r}; choose from {sorted(known)}")
    if args.run is not None:
        from covnet.messages import run_keyexpr  # validates like every key part

        try:
            run_keyexpr(args.run)
        except ValueError as exc:
            raise UsageError(f"--run: {exc}") from None
    # a whole network here: a fresh run id; a part of one (--nodes): the id every process
    # derives from the config, so the parts started on other hosts agree without being told
    run_id = args.run or (default_run_id(sc) if nodes is not None else new_run_id())
    try:
        status = up(
            sc,
            args.config,
            out,
            metrics,
            seed=args.seed,
            realtime=args.realtime,
            speed=args.speed,
            run_id=run_id,
            verbose=args.verbose,
            nodes=nodes,
            router=args.router,
            solver=args.solver if mobile else None,
            netns=args.netns,
        )
    except UpError as exc:
        _err(str(exc))
        status = EXIT_FAIL
    if passive:
        if (out / "association.json").is_file():
            _print_passive_up(out, figures=not args.no_figures)
        return status
    if mobile:
        if (out / "summary.json").is_file():
            from covnet.mobile.cli_entry import print_summary
            from covnet.mobile.results import load_summary as load_mobile_summary

            if not args.no_figures:
                from covnet.mobile.plots import make_figure

                print(f"figure: {make_figure(out)}")
            print_summary(out, load_mobile_summary(out))
        return status
    if (out / "summary.json").is_file():
        summary = load_summary(out)
        if not args.no_figures and summary["metrics"]:
            from covnet.plots import make_figures

            make_figures(out)
        _print_summary(out, summary)
    return status


def _print_passive_up(out: Path, *, figures: bool) -> None:
    """The summary of a passive network run, and its scene figure (the last associated scan)."""
    doc = json.loads((out / "association.json").read_text())
    sm = doc["summary"]
    print(
        f"{doc['method']}: {sm['scans']} scan(s), {sm['associated']} associated, "
        f"{sm['unassociated']} not associated (a list missing); "
        f"{sm['correct']}/{sm['truth']} targets associated correctly, "
        f"{sm['output'] - sm['correct']} wrong triple(s)"
    )
    if figures and "correct" in doc:  # a scored scan (the manager redraws the truth)
        from covnet.passive.plots import scene_figure

        print(f"figure: {scene_figure(out)}")
    print(f"run directory: {out}  (config {doc['config_hash']}, seed {doc['seed']})")


def cmd_replay(args: argparse.Namespace) -> int:
    from covnet.replay import replay_run

    run_dir = Path(args.run_dir)
    run_json = run_dir / "run.json"
    run_kind = json.loads(run_json.read_text()).get("kind") if run_json.is_file() else None
    if run_kind in ("mobile", "passive"):
        raise UsageError(
            f"{run_dir}: covnet replay re-fuses covariance-control runs; a {run_kind} run's "
            "replay is not built yet (its recording.mcap holds every message of the run)"
        )
    missing = [
        f
        for f in ("config.json", "run.json", "summary.json", "recording.mcap")
        if not (run_dir / f).is_file()
    ]
    if missing:
        raise UsageError(
            f"{run_dir}: not a recorded network run directory (missing {', '.join(missing)})"
        )
    from covnet.replay import ReplayError

    try:
        report = replay_run(run_dir, Path(args.out) if args.out else None)
    except ReplayError as exc:
        _err(str(exc))
        return EXIT_FAIL
    if report.identical:
        print(f"replayed {run_dir}: summary.json reproduced exactly ({report.out_dir})")
        return EXIT_OK
    print(f"replayed {run_dir}: summary.json DIFFERS ({report.out_dir}):", file=sys.stderr)
    for d in report.differences[:20]:
        print(f"  {d}", file=sys.stderr)
    return EXIT_FAIL


def cmd_compare(args: argparse.Namespace) -> int:
    from covnet import compare as cmp

    if _kind(args.config) in ("mobile", "passive"):
        raise UsageError("compare: fusion structures belong to covariance-control scenarios")
    sc = _load(args.config, args.seed)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    for m in modes:
        if m not in cmp.MODES:
            raise UsageError(f"--modes: unknown mode {m!r}; choose from {', '.join(cmp.MODES)}")
    if not modes:
        raise UsageError("--modes: name at least one mode")
    metric = (args.metric or [sc.allocation.metrics[0]])[-1]
    _metrics_for(sc, [metric])
    if args.runs < 2:
        raise UsageError(f"--runs: at least 2 runs for a NEES band, got {args.runs}")
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers: must be >= 1, got {args.workers}")
    out = _prepare_out(args.out, f"{sc.name}-compare", args.force)
    from covnet.batch import progress_printer

    total = len(modes) * args.runs
    progress = progress_printer("compare")

    print(
        f"comparing {', '.join(modes)} on {sc.name}: metric {metric}, {args.runs} seeds from "
        f"{sc.seed}, {total} runs",
        flush=True,
    )
    rows = cmp.compare(
        sc, modes, metric, args.runs, graph=args.graph, workers=args.workers, progress=progress
    )
    meta = {
        "scenario": sc.name,
        "metric": metric,
        "runs": args.runs,
        "first_seed": sc.seed,
        "graph": args.graph or sc.fusion.peer.graph,
    }
    title = (
        f"{sc.name}: fusion structures, metric {metric}, {args.runs} seeds, "
        f"peer graph {meta['graph']}"
    )
    return _batch_results(cmp, args, out, rows, meta, title)


def _batch_results(module, args, out, rows, meta, title) -> int:  # type: ignore[no-untyped-def]
    """The end of ``covnet compare`` / ``sweep``: the table files, the figure, the printout."""
    module.write_table(out, rows, meta)
    if not args.no_figures:
        module.make_figure(out, rows, title)
    if args.json:
        for r in rows:
            print(json.dumps(r))
    else:
        print(module.format_table(rows))
    print(f"results: {out}")
    return EXIT_OK


def cmd_sweep(args: argparse.Namespace) -> int:
    from covnet import sweep as sw
    from covnet.batch import progress_printer
    from covnet.config import SweepSpec

    if _kind(args.config) in ("mobile", "passive"):
        raise UsageError("sweep: the latency grid belongs to covariance-control scenarios")
    sc = _load(args.config, args.seed)
    if sc.fusion.mode == "peer":
        raise UsageError("sweep: fusion.mode peer has no fusion centre; sweep the centre modes")
    spec = sc.sweep or SweepSpec()
    metric = (args.metric or [spec.metric or sc.allocation.metrics[0]])[-1]
    _metrics_for(sc, [metric])
    for name in ("seeds", "workers"):
        v = getattr(args, name)
        if v is not None and v < 1:
            raise UsageError(f"--{name}: must be >= 1, got {v}")
    seeds = args.seeds or spec.seeds
    points = sw.grid(spec)
    out = _prepare_out(args.out, f"{sc.name}-sweep", args.force)
    print(
        f"sweeping {sc.name}: {len(points)} grid points x {seeds} seeds = "
        f"{len(points) * seeds} runs, metric {metric}"
        + ("" if sc.sweep else " (no sweep section in the config: the default grid)"),
        flush=True,
    )
    rows = sw.sweep(
        sc, metric=metric, seeds=seeds, workers=args.workers, progress=progress_printer("sweep")
    )
    meta = {
        "scenario": sc.name,
        "metric": metric,
        "seeds": seeds,
        "first_seed": sc.seed,
        "delay_kind": spec.delay_kind,
        "deadline_fraction": sc.network.deadline_fraction,
        "period_s": sc.period_s,
    }
    title = (
        f"{sc.name}: delay and loss ({spec.delay_kind} delays, both directions), "
        f"metric {metric}, {seeds} seeds, deadline {sc.network.deadline_fraction:g} T"
    )
    return _batch_results(sw, args, out, rows, meta, title)


def cmd_check(args: argparse.Namespace) -> int:
    import yaml

    from covnet.config import config_hash, normalised
    from covnet.security import preflight

    kind = _kind(args.config)
    if kind == "covariance_control":
        sc = _load(args.config)
        data, digest = normalised(sc), config_hash(sc)
    else:
        import importlib

        mod = importlib.import_module(f"covnet.{kind}.config")
        sc = mod.load(args.config)
        data, digest = mod.normalised(sc), mod.config_hash(sc)
    # the files security needs on this host (keys, certificates, passwords), for every node
    preflight(sc, ["manager", "world", "recorder", *sc.sensor_ids], args.config)  # type: ignore[arg-type]
    print(yaml.safe_dump(data, sort_keys=False), end="")
    print(f"# config hash: {digest}")
    return EXIT_OK


def cmd_plot(args: argparse.Namespace) -> int:
    from covnet.plots import make_figures

    run_dir = Path(args.run_dir)
    for stem in ("compare", "sweep"):  # a covnet compare / covnet sweep results directory
        if (run_dir / f"{stem}.json").is_file():
            import importlib

            module = importlib.import_module(f"covnet.{stem}")
            try:
                doc = json.loads((run_dir / f"{stem}.json").read_text())
                rows = doc["rows"]
            except (ValueError, KeyError) as exc:
                table = run_dir / f"{stem}.json"
                raise UsageError(f"{table}: not a {stem} table ({exc})") from None
            title = f"{doc.get('scenario', '')}: covnet {stem}, metric {doc.get('metric', '?')}"
            print(module.make_figure(run_dir, rows, title))
            return EXIT_OK
    missing = [
        f for f in ("summary.json", "arrays.npz", "config.json") if not (run_dir / f).is_file()
    ]
    if missing:
        raise UsageError(f"{run_dir}: not a complete run directory (missing {', '.join(missing)})")
    for p in make_figures(run_dir):
        print(p)
    return EXIT_OK


def _int_list(text: str) -> list[int]:
    try:
        vals = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from None
    if not vals or any(v < 1 or v > 24 for v in vals):
        raise argparse.ArgumentTypeError(f"sensor counts must be in 1..24, got {text!r}")
    return vals


def cmd_bench_up(args: argparse.Namespace) -> int:
    import tempfile

    from covnet.experiments.bench_up import run as bench_up_run

    sc = _load(args.config)
    with tempfile.TemporaryDirectory(prefix="covnet-bench-up-") as tmp:
        rows = bench_up_run(sc, args.config, Path(tmp), repeat=args.repeat, quiet=args.json)
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return EXIT_OK
    print(
        f"{'run':>4} {'scans':>6} {'scans/s':>8} {'wall s':>7} {'p50 ms':>7} {'p99 ms':>7} "
        f"{'core p50 ms':>11} {'core share':>10}"
    )
    for i, r in enumerate(rows):
        print(
            f"{i + 1:>4} {r['scans']:>6} {r['scans_per_s']:>8.0f} {r['wall_s']:>7.2f} "
            f"{r['scan_p50_ms']:>7.2f} {r['scan_p99_ms']:>7.2f} {r['core_p50_ms']:>11.3f} "
            f"{100 * r['core_share']:>9.1f}%"
        )
    med = sorted(r["scans_per_s"] for r in rows)[len(rows) // 2]
    print(f"median: {med:.0f} scans/s (loop: READY to last scan fused; wall includes start-up)")
    return EXIT_OK


def cmd_bench(args: argparse.Namespace) -> int:
    if args.target == "up":
        return cmd_bench_up(args)
    if args.target == "mobile":
        from covnet.mobile.cli_entry import bench_cmd as mobile_bench

        return mobile_bench(args.json)
    if args.target == "passive":
        from covnet.passive.cli_entry import bench_cmd as passive_bench

        return passive_bench(args.json)
    if args.target == "fusion":
        from covnet.experiments import bench_fusion

        rows = bench_fusion.run_bench(args.sensors or [8, 12, 16], repeat=max(args.repeat, 3))
        if args.json:
            for row in rows:
                print(json.dumps(row))
        else:
            print(bench_fusion.format_table(rows))
        return EXIT_OK
    args.sensors = args.sensors or [8, 12, 16, 20]
    from covnet.experiments import bench_allocation

    sc = _load(args.config)
    metrics = _metrics_for(sc, args.metric) if args.metric else None
    table = [(s.sigma_x_m, s.sigma_y_m, s.rho) for s in sc.sensors]

    def progress(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    rows = bench_allocation.run(
        table,
        args.sensors,
        metrics,
        n_problems=args.problems,
        repeat=args.repeat,
        progress=None if args.json else progress,
    )
    if args.json:
        keys = ("metric", "n_sensors", "median_s", "baseline_median_s", "peak_mb")
        for row in rows:
            print(json.dumps({k: row[k] for k in keys} | {"agree": row["agree"]}))
    else:
        print(
            "fast: per-decision allocate(P_pred, plan, P_d, metric) with plan = prepare(gains) "
            "built once per (N, metric), outside the timing"
        )
        print(
            f"{'metric':>10} {'N':>3} {'fast (ms)':>11} {'plain (ms)':>11} {'speedup':>8} "
            f"{'peak MB':>8}  agree"
        )
        for r in rows:
            print(
                f"{r['metric']:>10} {r['n_sensors']:>3} {1e3 * r['median_s']:>11.3f} "
                f"{1e3 * r['baseline_median_s']:>11.3f} "
                f"{r['baseline_median_s'] / r['median_s']:>7.1f}x {r['peak_mb']:>8.1f}  "
                f"{'yes' if r['agree'] else 'NO'}"
            )
    return EXIT_OK if all(r["agree"] for r in rows) else EXIT_FAIL


def _fusion_option(p: argparse.ArgumentParser) -> None:
    from covnet.config import FUSION_MODES

    p.add_argument(
        "--fusion",
        choices=FUSION_MODES,
        metavar="MODE",
        help="fusion structure, overriding the config's fusion.mode: central (raw measurements), "
        "info or ci (local tracks fused by information-matrix fusion or covariance "
        "intersection), peer (no fusion centre; see fusion.peer)",
    )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covnet",
        description="Covariance-control sensor allocation: simulate, benchmark, plot.",
    )
    p.add_argument("--version", action="version", version=f"covnet {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser("run", help="run a scenario in one process and write a run directory")
    r.add_argument("config", help="scenario YAML, e.g. configs/paper.yaml")
    r.add_argument("--out", help="run directory (default: a new folder under runs/)")
    r.add_argument(
        "--metric",
        action="append",
        metavar="NAME",
        help="run only this metric (repeatable; default: the config's allocation.metrics)",
    )
    r.add_argument("--seed", type=int, help="override the config's seed")
    _fusion_option(r)
    r.add_argument("--force", action="store_true", help="overwrite a non-empty --out directory")
    r.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    r.add_argument(
        "--solver",
        metavar="NAME",
        help="mobile scenarios: lp (default), lp_highs, closed_form or milp",
    )
    r.set_defaults(func=cmd_run)

    mc = sub.add_parser("mc", help="Monte Carlo evaluation of a mobile or passive scenario")
    mc.add_argument("config", help="configs/mobile.yaml or configs/passive.yaml")
    mc.add_argument(
        "--trials",
        type=int,
        metavar="N",
        help="seeds (mobile, default 20) or trials per cell (passive, default: config)",
    )
    mc.add_argument("--out", help="results directory (default: a new folder under runs/)")
    mc.add_argument("--force", action="store_true", help="overwrite a non-empty --out directory")
    mc.set_defaults(func=cmd_mc)

    u = sub.add_parser(
        "up", help="run the network: world, one process per sensor, the manager, over zenoh"
    )
    u.add_argument("config", help="scenario YAML, e.g. configs/paper.yaml")
    u.add_argument("--out", help="run directory (default: a new folder under runs/)")
    u.add_argument(
        "--metric",
        action="append",
        metavar="NAME",
        help="run only this metric (repeatable; default: the config's)",
    )
    u.add_argument("--seed", type=int, help="override the config's seed")
    _fusion_option(u)
    u.add_argument(
        "--solver",
        help="kind: mobile only: the decision's solver (lp, lp_highs, closed_form, milp)",
    )
    u.add_argument(
        "--realtime",
        action="store_true",
        help="pace scans by the config's period (default: lockstep, as fast as possible)",
    )
    u.add_argument("--speed", type=float, default=1.0, help="real-time speed factor (--realtime)")
    u.add_argument("--force", action="store_true", help="overwrite a non-empty --out directory")
    u.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    u.add_argument("--verbose", action="store_true", help="show every process's output")
    u.add_argument(
        "--run",
        help="run id (key prefix); default: a fresh one, or with --nodes the "
        "one every process derives from the config",
    )
    u.add_argument(
        "--router",
        help="router endpoint, overriding network.router "
        "(e.g. tcp/192.0.2.10:7447 to accept sensors from other hosts)",
    )
    u.add_argument(
        "--nodes",
        help="start only these here: comma-separated from manager, "
        "world, recorder, sensors, or sensor ids (default: all)",
    )
    u.add_argument(
        "--netns",
        action="store_true",
        help="each sensor in its own network namespace, linked to the manager's by an "
        "emulated link with network.latency's delays and loss (root; docs/netem.md)",
    )
    u.set_defaults(func=cmd_up)

    rp = sub.add_parser(
        "replay", help="re-fuse a network run's recorded measurements; check summary.json"
    )
    rp.add_argument("run_dir", help="a run directory written by covnet up (with recording.mcap)")
    rp.add_argument("--out", help="where to write the replayed run (default: RUN_DIR/replay)")
    rp.set_defaults(func=cmd_replay)

    cp = sub.add_parser(
        "compare",
        help="fusion structures side by side (central, info, ci, peer) over a Monte Carlo batch",
    )
    cp.add_argument("config", help="scenario YAML, e.g. configs/paper.yaml")
    cp.add_argument(
        "--modes",
        default="central,info,ci,peer-info,peer-ci",
        help="comma-separated from central, info, ci, ci-fast, peer-info, peer-ci "
        "(default: %(default)s)",
    )
    cp.add_argument("--runs", type=int, default=20, help="seeds per mode (default: %(default)s)")
    cp.add_argument(
        "--metric", action="append", metavar="NAME", help="allocation metric (default: the first)"
    )
    cp.add_argument(
        "--graph",
        choices=("full", "ring", "star", "custom"),
        help="peer modes' communication graph (default: the config's fusion.peer.graph)",
    )
    cp.add_argument("--seed", type=int, help="first seed (default: the config's)")
    cp.add_argument("--workers", type=int, help="processes (default: one per core)")
    cp.add_argument("--out", help="results directory (default: a new folder under runs/)")
    cp.add_argument("--force", action="store_true", help="overwrite a non-empty --out directory")
    cp.add_argument("--no-figures", action="store_true", help="skip compare.png")
    cp.add_argument("--json", action="store_true", help="one JSON row per mode")
    cp.set_defaults(func=cmd_compare)

    sw = sub.add_parser(
        "sweep",
        help="network latency: a grid of delay x loss x fusion mode x seeds (the config's sweep)",
    )
    sw.add_argument("config", help="scenario YAML with a sweep section, e.g. configs/latency.yaml")
    sw.add_argument("--seeds", type=int, help="seeds per grid point (default: sweep.seeds)")
    sw.add_argument("--metric", action="append", metavar="NAME", help="allocation metric")
    sw.add_argument("--seed", type=int, help="first seed (default: the config's)")
    sw.add_argument("--workers", type=int, help="processes (default: one per core)")
    sw.add_argument("--out", help="results directory (default: a new folder under runs/)")
    sw.add_argument("--force", action="store_true", help="overwrite a non-empty --out directory")
    sw.add_argument("--no-figures", action="store_true", help="skip sweep.png")
    sw.add_argument("--json", action="store_true", help="one JSON row per grid point")
    sw.set_defaults(func=cmd_sweep)

    c = sub.add_parser("check", help="validate a config; print it normalised with its hash")
    c.add_argument("config")
    c.set_defaults(func=cmd_check)

    pl = sub.add_parser("plot", help="(re)draw the figures of a run directory from its files")
    pl.add_argument("run_dir")
    pl.set_defaults(func=cmd_plot)

    b = sub.add_parser(
        "bench",
        help="benchmark: the allocator (default), the network ('up'), 'mobile' or 'passive'",
    )
    b.add_argument(
        "target",
        nargs="?",
        choices=["alloc", "up", "mobile", "passive", "fusion"],
        default="alloc",
        help="alloc: allocation decisions per metric and N; up: covnet up in lockstep; "
        "mobile: cost tensor and LP/MILP; passive: association methods; fusion: the batched "
        "covariance-intersection candidates of every subset against a scipy loop",
    )
    b.add_argument(
        "--sensors",
        type=_int_list,
        metavar="N,N,...",
        help="sensor counts (default 8,12,16,20; fusion: 8,12,16; beyond 8 the paper table "
        "cycles with both sigmas scaled by 1 + 0.5 (j // 8))",
    )
    b.add_argument(
        "--metric",
        action="append",
        metavar="NAME",
        help="only this metric (repeatable; default: every registered metric)",
    )
    b.add_argument("--config", default="configs/paper.yaml", help="sensor table and scenario")
    b.add_argument("--problems", type=int, default=5, help="decision problems per N (scans)")
    b.add_argument(
        "--repeat", type=int, default=3, help="timed repeats per problem (alloc) or whole runs (up)"
    )
    b.add_argument("--json", action="store_true", help="one JSON row per (metric, N)")
    b.set_defaults(func=cmd_bench)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    from covnet.config import ConfigError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except ConfigError as exc:
        print(f"covnet: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except UsageError as exc:
        _err(str(exc))
        return EXIT_USAGE
    except KeyboardInterrupt:
        _err("interrupted")
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
