"""The ``covnet`` command line: argparse, and the kind registry for everything else.

``main(argv) -> int`` so tests call it directly.  Exit status: 0 success, 1 a run failed,
2 a user's mistake (bad config, bad option, an existing run directory), 130 interrupted.
A user's mistake prints one readable message to stderr, never a traceback.

No command here knows a scenario kind: each loads the config through :mod:`covnet.kinds`
(which decides the kind once) and calls what the kind provides; a command a kind does not
have, or an option it does not take, is refused with a line that says so.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import covnet.errors  # noqa: F401  (first: a folder named covnet/ taken for it says so)

# isort: split
from covnet import __version__, kinds
from covnet.config import (
    ConfigError,
    ConfigWarning,
    endpoint_problem,
    hash_of,
    read_yaml,
    scheduler_problem,
)
from covnet.errors import UpError, UsageError
from covnet.processes import interrupts
from covnet.runs.rundir import CONFIG, RUN_INFO, config_mismatch, prepare_out, read_json, record_end

EXIT_OK, EXIT_FAIL, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_PIPE = 141
"""The reader of stdout went away (``covnet check CONFIG | head``): 128 + SIGPIPE, the status
of a Unix tool that the closed pipe stopped."""

BENCHES = {
    "alloc": "covariance_control",
    "fusion": "covariance_control",
    "search": "covariance_control",
    "multitarget": "covariance_control",
    "mobile": "mobile",
    "passive": "passive",
}
"""``covnet bench TARGET`` -> the kind whose ``bench:TARGET`` command it runs (``up`` is the
launcher's own, for a config of any kind)."""

BENCH_SENSORS_MAX = {"alloc": 24, "fusion": 24, "multitarget": 16, "search": 100_000, "up": 1024}
"""The largest ``--sensors`` count of each benchmark that takes one: ``alloc`` times the plain
baseline over all 2^N subsets and ``fusion`` a scipy loop over them, ``multitarget``'s sensor
table has 16 sensors, ``search`` runs its exact search only up to 40 and beyond that bounded
and greedy (N = 1000 takes seconds a decision), ``up`` starts a network of that size."""


def _err(msg: str) -> None:
    print(f"covnet: error: {msg}", file=sys.stderr)


def _note(msg: str) -> None:
    print(f"covnet: {msg}", file=sys.stderr)


def _options(args: argparse.Namespace, *names: str) -> dict[str, Any]:
    """The run options among ``names`` that the command line gave."""
    return {n: getattr(args, n, None) for n in names}


def _load(args: argparse.Namespace, *options: str) -> tuple[Any, Any]:
    """``(kind, config)`` of ``args.config`` with the given run ``options`` applied."""
    kind, cfg = kinds.load(args.config)
    return kind, kinds.apply_options(kind, cfg, args.config, **_options(args, *options))


RUN_OPTIONS = ("seed", "metric", "fusion", "solver")


def cmd_run(args: argparse.Namespace) -> int:
    """``covnet run``: the results are written once, when every scan is done (then
    ``run.json`` says ``completed``), the figures after them; a Ctrl-C before the results
    leaves nothing, one while drawing leaves the complete results."""
    kind, cfg = _load(args, *RUN_OPTIONS)
    out = prepare_out(args.out, cfg.name, args.force)
    try:
        status = int(kind.run(cfg, out, figures=not args.no_figures))
        if status == EXIT_OK and args.mcap:
            # start-up: the Foxglove SDK and the visual channels only for --mcap
            from covnet.runs.visual import write_run_mcap

            print(f"visual channels for Foxglove: {write_run_mcap(kind, cfg, out)}")
    except BaseException as exc:
        if not interrupts.caused(exc):
            raise
        if (out / RUN_INFO).is_file():
            record_end(out, "completed", "every scan done (figures interrupted)")
            _note(f"interrupted while drawing the figures: {out} holds the complete results "
                  f"(covnet plot {out} draws them)")  # fmt: skip
        else:
            _note("interrupted before the results were written: nothing written")
        raise
    if status == EXIT_OK:
        record_end(out, "completed", "every scan done")
    return status


def cmd_mc(args: argparse.Namespace) -> int:
    kind, cfg = _load(args, "seed", "metric", "fusion")
    return kinds.command(kind, "mc", "a Monte Carlo protocol")(args, cfg)


def cmd_compare(args: argparse.Namespace) -> int:
    kind, cfg = _load(args, "seed")
    return kinds.command(kind, "compare", "comparing fusion structures")(args, cfg)


def cmd_sweep(args: argparse.Namespace) -> int:
    kind, cfg = _load(args, "seed")
    return kinds.command(kind, "sweep", "the network-latency sweep")(args, cfg)


def cmd_replay(args: argparse.Namespace) -> int:
    run_dir = Path(args.run_dir)
    if not (run_dir / CONFIG).is_file():
        raise UsageError(f"{run_dir}: not a recorded network run directory (no {CONFIG})")
    try:
        data = read_json(run_dir / CONFIG)
    except ValueError as exc:
        raise UsageError(f"{run_dir / CONFIG}: not valid JSON ({exc})") from None
    _replayable(run_dir)
    kind, cfg = kinds.from_dict(data, str(run_dir / CONFIG))
    return kinds.command(kind, "replay", "replaying a recorded network run")(args, cfg)


def _replayable(run_dir: Path) -> None:
    """A run that ended (interrupted or failed) before its first scan has nothing to replay
    (and often no recording: Ctrl-C before READY): say so, exit 2.  A recorder that died
    (``run.json``'s ``lost``) is named before the differences it causes."""
    try:
        info = read_json(run_dir / RUN_INFO)
    except (OSError, ValueError):
        return  # the kind's replay names what is missing
    if not isinstance(info, dict) or info.get("status") not in ("interrupted", "failed"):
        return
    for ev in info.get("lost") or []:  # covnet up: a world or recorder died, not restarted
        if isinstance(ev, dict) and ev.get("node") == "recorder":
            _note(f"{run_dir}: {ev.get('ended', 'the recorder died')} (run.json: lost)")
    done = info.get("scans_completed")
    if isinstance(done, dict):
        done = sum(v for v in done.values() if isinstance(v, int))
    if done != 0:  # some scans, or not known (a directory rebuilt after a crash, or older)
        return
    raise UsageError(
        f"{run_dir}: nothing to replay: the run ended before its first scan (run.json: status "
        f"{info['status']}, no scan completed, ended: {info.get('ended', '?')})"
    )


def cmd_up(args: argparse.Namespace) -> int:
    # the launcher's modules, for the command that launches (start-up time of the others)
    from covnet.processes.process import default_run_id
    from covnet.processes.up import up

    kind, cfg = _load(args, *RUN_OPTIONS)
    if args.speed is not None and not args.realtime:
        raise UsageError(
            "--speed: scales the real-time clock, so it does nothing in lockstep; add --realtime"
        )
    if args.speed is not None and not args.speed > 0:
        raise UsageError(f"--speed: must be > 0, got {args.speed}")
    if args.router is not None and (problem := endpoint_problem(args.router)) is not None:
        raise UsageError(f"--router: {problem}")
    k = args.sensors_per_process
    if k is not None and k < 1:
        raise UsageError(f"--sensors-per-process: must be >= 1, got {k}")
    if k not in (None, 1) and args.netns:
        raise UsageError("--sensors-per-process: --netns runs each sensor in its own namespace")
    problem = kind.up_problem(cfg, realtime=args.realtime, netns=args.netns)
    if problem is not None:
        raise UsageError(problem)
    if args.netns:
        # only for --netns (start-up time)
        from covnet.processes.netns_launch import unsupported_reason

        if args.nodes or args.router:
            raise UsageError(
                "--netns runs the whole network on this machine, each sensor in its own "
                "namespace: not with --nodes or --router (for several hosts, leave out --netns)"
            )
        reason = unsupported_reason()
        if reason is not None:
            raise UsageError(reason)
    nodes = [n.strip() for n in args.nodes.split(",")] if args.nodes else None
    known = {"manager", "world", "recorder", "sensors", *cfg.sensor_ids}
    for n in nodes or []:
        if n not in known:
            raise UsageError(f"--nodes: unknown process {n!r}; choose from {sorted(known)}")
    if args.foxglove is not None:
        from covnet.runs.live import address_problem  # start-up: the SDK only for --foxglove

        if (problem := address_problem(args.foxglove)) is not None:
            raise UsageError(f"--foxglove: {problem}")
        if not cfg.network.record:
            raise UsageError(
                "--foxglove: the live view is served by the recorder, and this config has "
                "network.record: false"
            )
        if nodes is not None and "recorder" not in nodes:
            raise UsageError(
                "--foxglove: the live view is served by the recorder, which --nodes does not "
                "start here"
            )
    from covnet.wire.messages import new_run_id, run_keyexpr  # start-up: the network commands'

    if args.run is not None:
        try:
            run_keyexpr(args.run)  # validates like every key part
        except ValueError as exc:
            raise UsageError(f"--run: {exc}") from None
    out = prepare_out(args.out, cfg.name, args.force)
    # a whole network here: a fresh run id; a part of one (--nodes): the id every process
    # derives from the config, so the parts started on other hosts agree without being told
    run_id = args.run or (default_run_id(cfg) if nodes is not None else new_run_id())
    try:
        status = up(
            kind,
            cfg,
            args.config,
            out,
            options=_options(args, *RUN_OPTIONS),
            realtime=args.realtime,
            speed=args.speed or 1.0,
            run_id=run_id,
            verbose=args.verbose,
            nodes=nodes,
            router=args.router,
            netns=args.netns,
            sensors_per_process=k,
            foxglove=args.foxglove,
        )
    except UpError as exc:
        _err(str(exc))
        status = EXIT_FAIL
    kind.after_up(cfg, out, figures=not args.no_figures)
    return status


def cmd_check(args: argparse.Namespace) -> int:
    import yaml  # the check's printout only (start-up time of the other commands)

    from covnet.wire.messages import RESERVED_IDS  # start-up: the check's own
    from covnet.wire.security import preflight

    kind, cfg = kinds.load(args.config)
    data = kind.normalised(cfg)
    # the files security needs on this host (keys, certificates, passwords), for every node
    preflight(cfg, [*RESERVED_IDS, *cfg.sensor_ids], args.config)
    print(yaml.safe_dump(data, sort_keys=False), end="")
    print(f"# config hash: {hash_of(data)}")
    return EXIT_OK


def cmd_plot(args: argparse.Namespace) -> int:
    run_dir = Path(args.run_dir)
    if not (run_dir / CONFIG).is_file():
        raise UsageError(
            f"{run_dir}: not a complete run directory (missing {CONFIG}, which names its kind)"
        )
    # a corrupt config.json is a ConfigError (exit 2), as for replay
    kind, cfg = kinds.from_dict(read_yaml(run_dir / CONFIG), str(run_dir / CONFIG))
    stale = config_mismatch(run_dir, kinds.config_hash(cfg))
    if stale is not None:
        raise UsageError(stale)
    if args.point is not None:
        try:
            figures = kind.plot(run_dir, point=args.point)  # type: ignore[call-arg]
        except TypeError as exc:  # a kind whose plot takes no point
            if "point" not in str(exc):
                raise
            raise UsageError(f"--point: a {kind.title} directory has no per-point curves") from None
    else:
        figures = kind.plot(run_dir)
    for p in figures:
        print(p)
    return EXIT_OK


def cmd_export(args: argparse.Namespace) -> int:
    # start-up: the export's readers and writers for this command only
    from covnet.runs.export import export

    path = export(args.run_dir, args.format, args.out, args.episode)
    if path is not None:
        print(path)
    return EXIT_OK


def cmd_bench_up(args: argparse.Namespace) -> int:
    import tempfile  # only the benchmark needs these (start-up time of the other commands)

    from covnet.bench import up as bench_up

    kind, cfg = _load(args)
    k = args.sensors_per_process
    if k is not None and k < 1:
        raise UsageError(f"--sensors-per-process: must be >= 1, got {k}")
    with tempfile.TemporaryDirectory(prefix="covnet-bench-up-") as tmp:
        if args.sensors:
            rows = bench_up.run_sizes(
                kind, cfg, args.sensors, Path(tmp), repeat=args.repeat, per_process=k,
                quiet=args.json,
            )  # fmt: skip
        else:
            rows = bench_up.run(
                kind, cfg, args.config, Path(tmp), repeat=args.repeat, quiet=args.json,
                foxglove=args.foxglove,
            )  # fmt: skip
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return EXIT_OK
    if args.sensors:
        _print_sized(rows)
        return EXIT_OK
    print(
        f"{'run':>4} {'scans':>6} {'scans/s':>8} {'wall s':>7} {'p50 ms':>7} {'p99 ms':>7} "
        f"{'core p50 ms':>11} {'core share':>10}" + (f" {'foxglove':>8}" if args.foxglove else "")
    )
    for i, r in enumerate(rows):
        print(
            f"{i + 1:>4} {r['scans']:>6} {r['scans_per_s']:>8.0f} {r['wall_s']:>7.2f} "
            f"{r['scan_p50_ms']:>7.2f} {r['scan_p99_ms']:>7.2f} {r['core_p50_ms']:>11.3f} "
            f"{100 * r['core_share']:>9.1f}%" + (f" {r['foxglove']!s:>8}" if args.foxglove else "")
        )
    if not args.foxglove:
        med = sorted(r["scans_per_s"] for r in rows)[len(rows) // 2]
        print(f"median: {med:.0f} scans/s (loop: READY to last scan fused; wall includes start-up)")
        return EXIT_OK
    import statistics  # start-up: only for bench up --foxglove

    without = statistics.median(r["scans_per_s"] for r in rows if not r["foxglove"])
    with_fx = statistics.median(r["scans_per_s"] for r in rows if r["foxglove"])
    print(
        f"median: {without:.0f} scans/s without, {with_fx:.0f} with --foxglove "
        f"(ratio {with_fx / without:.3f}, {args.repeat} alternated pairs)"
    )
    return EXIT_OK


def _print_sized(rows: list[dict[str, Any]]) -> None:
    print(
        f"{'N':>5} {'K':>3} {'run':>3} {'scans/s':>8} {'p50 ms':>7} {'p99 ms':>7} "
        f"{'core ms':>8} {'probe/s':>8} {'probe p50':>9} {'probe p99':>9} {'ratio':>6}"
    )
    for r in rows:
        print(
            f"{r['n_sensors']:>5} {r['sensors_per_process']:>3} {r['run']:>3} "
            f"{r['scans_per_s']:>8.1f} {r['scan_p50_ms']:>7.2f} {r['scan_p99_ms']:>7.2f} "
            f"{r['core_p50_ms']:>8.3f} {r['probe_scans_per_s']:>8.1f} {r['probe_p50_ms']:>9.2f} "
            f"{r['probe_p99_ms']:>9.2f} {r['ratio']:>6.2f}"
        )
    print(
        "covnet: READY to last scan fused, every sensor enabled every scan; probe: the same "
        "pattern on bare zenoh pub/sub, same sessions and hosting; ratio = covnet / probe"
    )


BENCH_TAKES: dict[str, frozenset[str]] = {
    "alloc": frozenset({"sensors", "metric", "problems", "repeat", "config", "json"}),
    "up": frozenset({"sensors", "repeat", "config", "json", "foxglove", "sensors_per_process"}),
    "soak": frozenset(
        {"config", "metric", "scans", "realtime_s", "speed", "interval", "windows", "work", "json"}
    ),
    "cluster": frozenset({"config", "repeat", "json"}),
    "fusion": frozenset({"sensors", "repeat", "json"}),
    "search": frozenset(
        {"sensors", "metric", "search", "exact_cap", "problems", "repeat", "config", "json"}
    ),
    "multitarget": frozenset(
        {"sensors", "metric", "targets", "problems", "repeat", "config", "json"}
    ),
    "mobile": frozenset({"json"}),
    "passive": frozenset({"json"}),
}
"""The options each ``covnet bench TARGET`` takes (every other one is refused)."""

BENCH_DEFAULTS: dict[str, Any] = {
    "sensors": None,
    "metric": None,
    "search": None,
    "exact_cap": None,
    "targets": None,
    "config": "configs/paper.yaml",
    "problems": 5,
    "repeat": 3,
    "json": False,
    "foxglove": False,
    "sensors_per_process": None,
    "scans": 20_000,
    "realtime_s": 600.0,
    "speed": 10.0,
    "interval": 2.0,
    "windows": 10,
    "work": None,
}
"""The value of a ``covnet bench`` option not given (cluster: its own config and repeat)."""


def _bench_options(args: argparse.Namespace) -> None:
    """Refuse an option ``bench args.target`` does not take; fill in the ones not given."""
    given = [d for d in BENCH_DEFAULTS if hasattr(args, d)]
    for dest in given:
        if dest not in BENCH_TAKES[args.target]:
            takes = ", ".join(f"--{d.replace('_', '-')}" for d in sorted(BENCH_TAKES[args.target]))
            raise UsageError(
                f"--{dest.replace('_', '-')}: bench {args.target} does not take this option "
                f"(its options: {takes})"
            )
    if args.target == "cluster":  # the sweep's own config; alternations
        for dest, value in (("config", "configs/latency.yaml"), ("repeat", 4)):
            if not hasattr(args, dest):
                setattr(args, dest, value)
    for dest, value in BENCH_DEFAULTS.items():
        if not hasattr(args, dest):
            setattr(args, dest, value)


def cmd_bench(args: argparse.Namespace) -> int:
    _bench_options(args)
    for name in ("problems", "repeat"):
        if getattr(args, name) < 1:
            raise UsageError(f"--{name}: must be >= 1, got {getattr(args, name)}")
    if args.sensors is not None:
        top = BENCH_SENSORS_MAX[args.target]  # (one that takes none: refused above)
        if max(args.sensors) > top:
            raise UsageError(
                f"--sensors: bench {args.target} takes counts up to {top}, got {max(args.sensors)}"
            )
    if args.exact_cap is not None and not args.exact_cap > 0:
        raise UsageError(f"--exact-cap: must be > 0 seconds, got {args.exact_cap}")
    if args.foxglove and (args.target != "up" or args.sensors):
        raise UsageError("--foxglove: only for bench up (the paper network, without --sensors)")
    if args.target == "up":
        return cmd_bench_up(args)
    if args.target == "cluster":
        # dask: only for this benchmark (start-up)
        from covnet.bench import cluster as bench_cluster

        return bench_cluster.main(args)
    if args.target == "soak":
        # start-up: the soak's module (numpy, the recording reader) only for this benchmark
        from covnet.bench import soak as bench_soak

        return bench_soak.main(args)
    kind = kinds.get(BENCHES[args.target])
    return kinds.command(kind, f"bench:{args.target}", f"the {args.target} benchmark")(args, None)


def _int_list(text: str) -> list[int]:
    try:
        vals = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from None
    if not vals or any(v < 1 for v in vals):
        raise argparse.ArgumentTypeError(f"sensor counts must be >= 1, got {text!r}")
    return vals  # each benchmark's largest count: BENCH_SENSORS_MAX, checked in cmd_bench


def _cluster_address(text: str) -> str:
    """``--cluster``: checked while the options are parsed, before any directory is made."""
    problem = scheduler_problem(text)
    if problem is not None:
        raise argparse.ArgumentTypeError(f"{text}: {problem}")
    return text


def _batch_options(p: argparse.ArgumentParser, seeds: str) -> None:
    """The batch layer's options (:mod:`covnet.batches.trials`), the same for sweep, mc and
    compare."""
    p.add_argument(
        "--cluster",
        type=_cluster_address,
        metavar="ADDRESS",
        help="run the trials on the Dask distributed scheduler at ADDRESS (tcp://host:port; "
        "workers need covnet installed; pip install 'covnet[cluster]'); default: this "
        "machine's cores",
    )
    p.add_argument(
        "--ci-width",
        type=float,
        metavar="X",
        help=f"add {seeds} in batches until every point's 95 %% confidence interval on the "
        "headline metric (sweep, compare: RMSE after the burn-in, m; mobile mc: overall "
        "RMSE, m; passive mc: the share of targets associated, p) is narrower than X",
    )
    p.add_argument(
        "--max-seeds",
        type=int,
        metavar="N",
        help="with --ci-width: at most N per point (default 100)",
    )


def _out_options(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--out", help=f"{what} directory (default: a new folder under runs/)")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the contents of a non-empty --out directory (an earlier covnet output)",
    )


def _run_options(p: argparse.ArgumentParser, metric_help: str) -> None:
    """The options that change what a run computes (each a change of the config)."""
    p.add_argument("--metric", action="append", metavar="NAME", help=metric_help)
    p.add_argument("--seed", type=int, help="override the config's seed")
    p.add_argument(
        "--fusion",
        metavar="MODE",
        help="covariance-control scenarios: the fusion structure, overriding fusion.mode: "
        "central (raw measurements), info or ci (local tracks fused by information-matrix "
        "fusion or covariance intersection), peer (no fusion centre; see fusion.peer)",
    )
    p.add_argument(
        "--solver",
        metavar="NAME",
        help="mobile scenarios: the decision's solver (lp, lp_highs, closed_form, milp)",
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
    _out_options(r, "run")
    _run_options(r, "run only this metric (repeatable; default: the config's allocation.metrics)")
    r.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    r.add_argument(
        "--mcap",
        action="store_true",
        help="also write run.mcap: the run's scans as Foxglove draws them (scene, numbers, log)",
    )
    r.set_defaults(func=cmd_run)

    mc = sub.add_parser("mc", help="Monte Carlo evaluation of a scenario over seeds or trials")
    mc.add_argument(
        "config", help="e.g. configs/multitarget.yaml, configs/mobile.yaml, configs/passive.yaml"
    )
    mc.add_argument(
        "--trials",
        type=int,
        metavar="N",
        help="seeds (covariance control: from the config's, default 20; mobile: 0..N-1, "
        "default 20) or trials per cell (passive, default: config)",
    )
    mc.add_argument(
        "--metric",
        action="append",
        metavar="NAME",
        help="covariance control: only this allocation metric (repeatable; default: the "
        "config's allocation.metrics)",
    )
    mc.add_argument(
        "--seed",
        type=int,
        help="first seed (default: the config's; passive: the seed of every trial's stream; "
        "mobile runs seeds 0..N-1)",
    )
    mc.add_argument(
        "--fusion",
        metavar="MODE",
        help="covariance control: the fusion structure, overriding fusion.mode (central, info, "
        "ci; with targets: central or info)",
    )
    mc.add_argument("--workers", type=int, help="processes (default: one per core)")
    _batch_options(mc, "seeds (passive: trials)")
    _out_options(mc, "results")
    mc.add_argument("--no-figures", action="store_true", help="skip the figures")
    mc.add_argument(
        "--json",
        action="store_true",
        help="JSON Lines on stdout: one JSON object per line (covariance control: per metric "
        "and target; mobile: per target and overall; passive: per cell and method)",
    )
    mc.set_defaults(func=cmd_mc)

    u = sub.add_parser(
        "up", help="run the network: world, one process per sensor, the manager, over zenoh"
    )
    u.add_argument("config", help="scenario YAML, e.g. configs/paper.yaml")
    _out_options(u, "run")
    _run_options(u, "run only this metric (repeatable; default: the config's)")
    u.add_argument(
        "--realtime",
        action="store_true",
        help="pace scans by the config's period (default: lockstep, as fast as possible)",
    )
    u.add_argument(
        "--speed", type=float, help="with --realtime: the clock's speed factor (default 1)"
    )
    u.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    u.add_argument("--verbose", action="store_true", help="show every process's output")
    u.add_argument(
        "--sensors-per-process",
        type=int,
        metavar="K",
        help="sensors one sensor process hosts, each with its own session, liveliness token and "
        "heartbeat (default: 1 for up to 16 sensors, else about two sensor processes per core)",
    )
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
    u.add_argument(
        "--foxglove",
        nargs="?",
        const="127.0.0.1:8765",
        metavar="HOST:PORT",
        help="serve the run live over the Foxglove WebSocket protocol (default 127.0.0.1:8765): "
        "the scene, the numbers and the status lines, as the recording holds them",
    )
    u.set_defaults(func=cmd_up)

    rp = sub.add_parser(
        "replay", help="rebuild a network run of any kind from its recording; check it exactly"
    )
    rp.add_argument("run_dir", help="a run directory written by covnet up (with recording.mcap)")
    rp.add_argument(
        "--out", help="where to write the replayed run (default: RUN_DIR/replay, replaced)"
    )
    rp.add_argument(
        "--force", action="store_true", help="replace the contents of a non-empty --out"
    )
    rp.set_defaults(func=cmd_replay)

    cp = sub.add_parser(
        "compare",
        help="fusion structures side by side (central, info, ci, peer) over a Monte Carlo batch",
    )
    cp.add_argument("config", help="scenario YAML, e.g. configs/paper.yaml")
    cp.add_argument(
        "--modes",
        help="comma-separated fusion structures: a fusion rule at a centre (central, info, ci), "
        "ci-fast, or peer-<rule> (peer-info, peer-ci); default: all but ci-fast",
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
    _batch_options(cp, "seeds")
    _out_options(cp, "results")
    cp.add_argument("--no-figures", action="store_true", help="skip compare.png")
    cp.add_argument(
        "--json",
        action="store_true",
        help="JSON Lines on stdout: one JSON object per line, a row per mode",
    )
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
    _batch_options(sw, "seeds")
    _out_options(sw, "results")
    sw.add_argument("--no-figures", action="store_true", help="skip sweep.png")
    sw.add_argument(
        "--json",
        action="store_true",
        help="JSON Lines on stdout: one JSON object per line, a row per grid point",
    )
    sw.set_defaults(func=cmd_sweep)

    c = sub.add_parser("check", help="validate a config; print it normalised with its hash")
    c.add_argument("config")
    c.set_defaults(func=cmd_check)

    pl = sub.add_parser("plot", help="(re)draw the figures of a run directory from its files")
    pl.add_argument("run_dir")
    pl.add_argument(
        "--point",
        metavar="TEXT",
        help="sweep, compare: draw curves.png (per-scan RMSE and NEES with 95 %% bands) for "
        "every point whose key contains TEXT, e.g. delay_ms=350,loss=0,mode=central",
    )
    pl.set_defaults(func=cmd_plot)

    ex = sub.add_parser(
        "export",
        help="a run directory's truths and tracks as CSV or as Stone Soup objects",
        description="Every episode's truths and tracks (per scan: time, state x, vx, y, vy and "
        "the track's covariance) as a CSV (documented columns) or as Stone Soup GroundTruthPath "
        "and Track objects in Stone Soup's YAML (needs: pip install 'covnet[stonesoup]').",
    )
    ex.add_argument("run_dir", help="a run directory of covnet run or covnet up")
    ex.add_argument("--format", choices=["csv", "stonesoup"], default="csv", help="default csv")
    ex.add_argument(
        "--out",
        metavar="PATH",
        help="the file to write, '-' for stdout (default: export.csv or export.stonesoup.yaml "
        "in the run directory)",
    )
    ex.add_argument(
        "--episode", metavar="NAME", help="only this episode, e.g. a metric (default: every one)"
    )
    ex.set_defaults(func=cmd_export)

    b = sub.add_parser(
        "bench",
        help="benchmark: the allocator (default), the network ('up'), 'fusion', 'search', "
        "'multitarget', 'mobile', 'passive', 'soak' or 'cluster'",
        description="Each option says which benchmarks take it; an option the benchmark does "
        "not take is refused.",
        argument_default=argparse.SUPPRESS,  # given or not: cmd_bench checks, then fills in
    )
    b.add_argument(
        "target",
        nargs="?",
        choices=list(BENCH_TAKES),
        default="alloc",
        help="alloc: allocation decisions per metric and N; up: covnet up in lockstep; "
        "mobile: cost tensor and LP/MILP; passive: association methods; fusion: the batched "
        "covariance-intersection candidates of every subset against a scipy loop; search: "
        "branch and bound / bounded / greedy against the exhaustive search (N up to 1000); "
        "multitarget: the assignment allocator over T targets against plain enumeration; "
        "soak: a long lockstep and a long real-time covnet up, memory, descriptors and "
        "latency of every process over time; cluster: a sweep's trials per second on the local "
        "pool and on a local 2-worker Dask cluster, alternated, and each one's per-task "
        "overhead",
    )

    def takes(dest: str) -> str:
        return "[" + ", ".join(t for t, opts in BENCH_TAKES.items() if dest in opts) + "] "

    b.add_argument(
        "--sensors",
        type=_int_list,
        metavar="N,N,...",
        help=takes("sensors") + "sensor counts (default 8,12,16,20; fusion: 8,12,16; search: "
        "8,...,32; beyond 8 the paper table cycles with both sigmas scaled by 1 + 0.5 (j // 8)); "
        "at most 24 for alloc and fusion, 16 for multitarget",
    )
    b.add_argument(
        "--metric",
        action="append",
        metavar="NAME",
        help=takes("metric") + "only this metric (repeatable; default: every registered metric)",
    )
    b.add_argument(
        "--search",
        action="append",
        metavar="NAME",
        help=takes("search") + "only this search (exact, bounded, greedy; repeatable)",
    )
    b.add_argument(
        "--exact-cap",
        type=float,
        metavar="S",
        help=takes("exact_cap") + "stop an exact decision after S seconds, counted as not exact "
        "in n_exact and timed at the cap (default 60)",
    )
    b.add_argument(
        "--targets",
        type=_int_list,
        metavar="T,T,...",
        help=takes("targets") + "numbers of targets (default 3, the spec's scenario; up to 8)",
    )
    b.add_argument(
        "--config",
        help=takes("config") + "sensor table and scenario (default configs/paper.yaml; "
        "cluster: configs/latency.yaml)",
    )
    b.add_argument(
        "--problems", type=int, help=takes("problems") + "decision problems per N (default 5)"
    )
    b.add_argument(
        "--repeat",
        type=int,
        help=takes("repeat") + "timed repeats per problem (alloc, default 3), whole runs (up), "
        "alternations (cluster, default 4)",
    )
    b.add_argument(
        "--json",
        action="store_true",
        help=takes("json") + "JSON Lines on stdout: one JSON object per line, a row per "
        "measurement (alloc: per metric and N)",
    )
    b.add_argument(
        "--foxglove",
        action="store_true",
        help=takes("foxglove") + "pairs of runs without and with covnet up --foxglove, "
        "alternated, and the ratio of their median scans/s",
    )
    b.add_argument(
        "--sensors-per-process",
        type=int,
        metavar="K",
        help=takes("sensors_per_process") + "sensors per sensor process (default: covnet up's)",
    )
    b.add_argument(
        "--scans", type=int, help=takes("scans") + "lockstep scans (0: none; default 20000)"
    )
    b.add_argument(
        "--realtime-s",
        type=float,
        help=takes("realtime_s") + "seconds of the real-time run (0: none; default 600)",
    )
    b.add_argument("--speed", type=float, help=takes("speed") + "the real-time run's speed (10)")
    b.add_argument(
        "--interval", type=float, help=takes("interval") + "seconds between samples (default 2)"
    )
    b.add_argument("--windows", type=int, help=takes("windows") + "latency windows per run (10)")
    b.add_argument("--work", help=takes("work") + "keep the soak's run directories here")
    b.set_defaults(func=cmd_bench)
    return p


def _show_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: Any = None,
    line: str | None = None,
) -> None:
    """A config warning as one line (``covnet: warning: <path>: <message>``); others as
    Python prints them."""
    if issubclass(category, ConfigWarning):
        print(f"covnet: warning: {message}", file=sys.stderr)
        return
    _python_showwarning(message, category, filename, lineno, file, line)


_python_showwarning = warnings.showwarning


def _stdout_closed() -> bool:
    """True when stdout is a pipe whose reader has gone (so the ``BrokenPipeError`` was our
    output's, not some other pipe's): its write end then polls ``POLLERR``.  stdout is then
    pointed at ``/dev/null``, so that the interpreter's last flush at exit prints nothing."""
    import select  # start-up: only after a broken pipe
    import stat

    try:
        fd = sys.stdout.fileno()
        if not stat.S_ISFIFO(os.fstat(fd).st_mode):
            return False
        poll = select.poll()
        poll.register(fd, select.POLLOUT)
        if not any(ev & select.POLLERR for _, ev in poll.poll(0)):
            return False
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, fd)
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        return False
    return True


def main(argv: Sequence[str] | None = None) -> int:
    if threading.current_thread() is threading.main_thread():
        # SIGINT and SIGTERM raise KeyboardInterrupt; one inside a weakref callback is raised
        # again, not printed and lost
        interrupts.deliver_late_interrupts()
    parser = build_parser()
    args = parser.parse_args(argv)
    warnings.showwarning = _show_warning
    try:
        status = int(args.func(args))
        # the output still buffered is written here, where a reader that has gone is told
        # from a failure (not at the interpreter's exit: "Exception ignored", status 120)
        sys.stdout.flush()
        return status
    except ConfigError as exc:
        print(f"covnet: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except UsageError as exc:
        _err(str(exc))
        return EXIT_USAGE
    except UpError as exc:  # a network run that failed (bench up, bench soak): its reason
        _err(str(exc))
        return EXIT_FAIL
    except BrokenPipeError:
        if not _stdout_closed():
            raise
        return EXIT_PIPE
    except BaseException as exc:  # a Ctrl-C, or an extension's stand-in for one it swallowed
        if not interrupts.caused(exc):
            raise
        interrupts.answered()
        _err("interrupted")
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
