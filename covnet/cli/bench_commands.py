"""``covnet bench TARGET``: which options each benchmark takes (the others are refused), their
defaults, and the command, which runs ``up``, ``soak`` and ``cluster`` itself and every other
benchmark through its kind (``bench:TARGET``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from covnet import kinds
from covnet.cli.common import EXIT_OK, _load
from covnet.errors import UsageError

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

BENCH_SENSORS_MAX = {"alloc": 24, "fusion": 24, "multitarget": 256, "search": 100_000, "up": 1024}
"""The largest ``--sensors`` count of each benchmark that takes one: ``alloc`` times the plain
baseline over all 2^N subsets and ``fusion`` a scipy loop over them, ``multitarget``'s sensor
table has 16 sensors, ``search`` runs its exact search only up to 40 and beyond that bounded
and greedy (N = 1000 takes seconds a decision), ``up`` starts a network of that size."""


def cmd_bench_up(args: argparse.Namespace) -> int:
    import tempfile  # only the benchmark needs these (start-up time of the other commands)

    from covnet.bench import up as bench_up

    kind, cfg = _load(args)
    k = args.sensors_per_process
    if k is not None and k < 1:
        raise UsageError(f"--sensors-per-process: must be >= 1, got {k}")
    if args.steady:
        return _bench_up_steady(kind, cfg, args, k)
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


def _bench_up_steady(kind: Any, cfg: Any, args: argparse.Namespace, k: int | None) -> int:
    """``bench up --sensors N,... --steady`` (:mod:`covnet.bench.budget`)."""
    import tempfile  # only the benchmark needs these (start-up time of the other commands)

    from covnet.bench import budget

    with tempfile.TemporaryDirectory(prefix="covnet-bench-steady-") as tmp:
        rows = budget.run_steady(
            kind, cfg, args.sensors, Path(tmp), repeat=args.repeat, per_process=k,
            scans=args.scans, quiet=args.json,
        )  # fmt: skip
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return EXIT_OK
    print(
        f"{'N':>5} {'K':>3} {'run':>3} {'CPU ms/scan':>11} {'scans/s':>8} {'cores':>5} "
        f"{'probe ms':>8} {'probe/s':>8} {'cores':>5} {'ratio':>6} {'budget ms':>9} {'cut':>5}"
    )
    for r in rows:
        print(
            f"{r['n_sensors']:>5} {r['sensors_per_process']:>3} {r['run']:>3} "
            f"{r['cpu_ms_per_scan']:>11.2f} {r['scans_per_s']:>8.1f} {r['cores']:>5.2f} "
            f"{r['probe_cpu_ms_per_scan']:>8.2f} {r['probe_scans_per_s']:>8.1f} "
            f"{r['probe_cores']:>5.2f} {r['ratio']:>6.2f} {r['budget_ms_per_scan']:>9.2f} "
            f"{100 * r['cut_needed']:>4.0f}%"
        )
    print(
        "the steady middle of long runs: covnet's CPU a scan over every process (by role with "
        "--json), the probe's from a long run less a short one; budget: the CPU a scan covnet "
        "could use at one half of the probe's scans/s on the cores it uses; cut: how much less "
        "that is"
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
    "up": frozenset(
        {"sensors", "repeat", "config", "json", "foxglove", "sensors_per_process", "steady",
         "scans"}
    ),
    "soak": frozenset(
        {"config", "metric", "scans", "realtime_s", "speed", "interval", "windows", "work", "json"}
    ),
    "cluster": frozenset({"config", "repeat", "json"}),
    "fusion": frozenset({"sensors", "repeat", "json"}),
    # search and multitarget generate their problems: no config
    "search": frozenset(
        {"sensors", "metric", "search", "exact_cap", "problems", "repeat", "json", "clock"}
    ),
    "multitarget": frozenset(
        {"sensors", "metric", "targets", "search", "problems", "repeat", "json", "clock"}
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
    "clock": "wall",
    "targets": None,
    "config": "configs/paper.yaml",
    "problems": 5,
    "repeat": 3,
    "json": False,
    "foxglove": False,
    "sensors_per_process": None,
    "scans": None,  # soak: 20 000; up --steady: 3 000
    "steady": False,
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


#: the most ``--problems`` and ``--repeat`` a benchmark takes (its problems are drawn before
#: it starts: a mistyped count failed in numpy instead of being named)
BENCH_COUNT_MAX = 10_000


def cmd_bench(args: argparse.Namespace) -> int:
    # a default config missing here is said after the options' values are checked
    default_config = not hasattr(args, "config") and "config" in BENCH_TAKES[args.target]
    _bench_options(args)
    for name in ("problems", "repeat"):
        if getattr(args, name) < 1:
            raise UsageError(f"--{name}: must be >= 1, got {getattr(args, name)}")
        if getattr(args, name) > BENCH_COUNT_MAX:  # the problems are drawn up front
            raise UsageError(f"--{name}: at most {BENCH_COUNT_MAX}, got {getattr(args, name)}")
    if args.sensors is not None:
        top = BENCH_SENSORS_MAX[args.target]  # (one that takes none: refused above)
        if max(args.sensors) > top:
            raise UsageError(
                f"--sensors: bench {args.target} takes counts up to {top}, got {max(args.sensors)}"
            )
    if args.metric:  # a metric named twice is timed once (as covnet run takes it), one row
        args.metric = list(dict.fromkeys(args.metric))
    if args.exact_cap is not None and not args.exact_cap > 0:
        raise UsageError(f"--exact-cap: must be > 0 seconds, got {args.exact_cap}")
    if args.sensors_per_process is not None and not args.sensors:
        # without --sensors the config's own network runs, hosted as its config says
        raise UsageError(
            "--sensors-per-process: only with --sensors (the bench networks of N sensors); "
            "without it bench up runs the config's network as covnet up hosts it"
        )
    if args.target == "cluster" and args.repeat < 2:  # it ran 2 and said nothing
        raise UsageError(
            f"--repeat: bench cluster alternates the local pool and Dask, at least 2 pairs, "
            f"got {args.repeat}"
        )
    if args.target == "up" and (args.steady or args.scans is not None) and not args.sensors:
        flag = "--steady" if args.steady else "--scans"
        raise UsageError(f"{flag}: only with --sensors (bench up --sensors N,... --steady)")
    if args.target == "up" and args.scans is not None and not args.steady:
        raise UsageError("--scans: bench up takes it with --steady (its steady runs' scans)")
    if args.foxglove and (args.target != "up" or args.sensors):
        raise UsageError("--foxglove: only for bench up (the paper network, without --sensors)")
    if default_config and not Path(args.config).is_file():
        raise UsageError(
            f"--config: not given, and the default {args.config} is not in this directory (a "
            "path in the covnet checkout): run from the checkout, or give --config PATH"
        )
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
