"""The covariance-control kind's commands: ``covnet run``, ``compare``, ``sweep``, ``replay``,
``bench alloc`` and ``bench fusion`` for its configs, and what ``covnet up`` and ``covnet plot``
do with its run directories.  :mod:`covnet.covariance_control.kind` registers them; the CLI
(:mod:`covnet.cli.app`) parses the arguments and calls them through the kind registry.

Each returns an exit status (0 success, 1 a run failed); a user's mistake raises
:class:`~covnet.errors.UsageError`.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from covnet.core.metrics import METRICS
from covnet.covariance_control.config import Scenario, from_dict, load
from covnet.covariance_control.decentral_sim import run_mode
from covnet.covariance_control.model import build_model
from covnet.covariance_control.results import write_run
from covnet.covariance_control.simulate import MetricRun, shared_trajectory
from covnet.errors import UsageError
from covnet.processes.forked import map_in_forks
from covnet.runs.rundir import (
    CONFIG,
    SUMMARY,
    json_line,
    load_arrays,
    read_json,
)

CURVES = "curves.npz"
"""The per-scan RMSE and NEES curves of every point of a sweep or compare, with their bands."""

# The figures (matplotlib), the batch commands (:mod:`covnet.covariance_control.batch_commands`:
# ``mc``, ``compare``, ``sweep``), the replay (the MCAP reader) and the benchmarks are imported
# by the commands that use them: start-up time of ``covnet run``.

EXIT_OK, EXIT_FAIL = 0, 1


def run(sc: Scenario, out: Path, *, figures: bool) -> int:
    """``covnet run``: every metric of ``allocation.metrics`` in this process (the fusion mode
    of ``fusion``; slow links in simulated time); writes the run directory."""
    if sc.surveillance is not None:
        return run_surveillance(sc, out, figures=figures)
    if sc.multitarget:
        return run_targets(sc, out, figures=figures)
    model = build_model(sc)
    traj = shared_trajectory(model)
    slow = not sc.network.latency.is_ideal(sc.sensor_ids)
    if slow and not sc.fusion.has_centre:
        raise UsageError("network.latency: peer mode has no fusion centre; latency runs need one")

    def one(m: str) -> tuple[MetricRun, dict[str, MetricRun] | None, dict[str, int] | None, float]:
        """Metric ``m``'s run: ``(run, every peer node's run, the link counts, seconds)``."""
        t0 = time.perf_counter()
        if slow:
            from covnet.covariance_control.latency_sim import run_latency  # start-up: slow links

            run, counts = run_latency(sc, m, model)
            return run, None, counts.as_dict(), time.perf_counter() - t0
        run, nodes = run_mode(sc, m, model)
        return run, nodes, None, time.perf_counter() - t0

    # the metrics are independent runs of the same model: on the cores at once
    metrics = list(sc.allocation.metrics)
    runs = {}
    node_runs = {}
    latency: dict[str, dict[str, int]] = {}
    for m, (r, nodes, counts, seconds) in zip(metrics, map_in_forks(one, metrics), strict=True):
        runs[m] = r
        if nodes is not None:
            node_runs[m] = nodes
        if counts is not None:
            latency[m] = counts
        # the summary's allocation_rate, formatted alike (63.75 % printed 63.8 here, 63.7 there)
        rate = 100 * float(r.enabled.sum() / r.enabled.size)
        print(f"{m:>10}: {sc.scans} scans in {seconds:.2f} s, allocation rate {rate:.1f} %")
    summary = write_run(
        out,
        sc,
        traj,
        runs,
        extra={"latency": latency} if latency else None,
        run_info={"mode": "in-process"},
        node_runs=node_runs,
    )
    if figures:
        from covnet.covariance_control.plots import make_figures  # matplotlib: start-up

        make_figures(out)
    print_summary(out, summary)
    return EXIT_OK


def run_targets(sc: Scenario, out: Path, *, figures: bool) -> int:
    """``covnet run`` of a config with ``targets:``: every metric's many-target run in this
    process; writes the run directory (:func:`covnet.covariance_control.results.
    write_targets_run`) and its figures."""
    # start-up: the many-target steps and results only for configs with targets
    from covnet.covariance_control import targets
    from covnet.covariance_control.results import write_targets_run
    from covnet.covariance_control.simulate import run_targets as simulate_targets

    tm = targets.build(sc)
    slow = not sc.network.latency.is_ideal(sc.sensor_ids)

    def one(m: str) -> tuple[Any, dict[str, int] | None, float]:
        """Metric ``m``'s many-target run: ``(run, the link counts, seconds)``."""
        t0 = time.perf_counter()
        if slow:
            from covnet.covariance_control.latency_sim import run_targets_latency  # start-up

            run, counts = run_targets_latency(sc, m, tm)
            return run, counts.as_dict(), time.perf_counter() - t0
        return simulate_targets(sc, m, tm), None, time.perf_counter() - t0

    metrics = list(sc.allocation.metrics)
    runs = {}
    latency: dict[str, dict[str, int]] = {}
    for m, (r, counts, seconds) in zip(metrics, map_in_forks(one, metrics), strict=True):
        runs[m] = r
        if counts is not None:
            latency[m] = counts
        print(
            f"{m:>10}: {sc.scans} scans x {len(tm.targets)} targets in "
            f"{seconds:.2f} s, allocation rate {100.0 * r.enabled.mean():.1f} %"
        )
    summary = write_targets_run(
        out,
        sc,
        tm,
        runs,
        extra={"latency": latency} if latency else None,
        run_info={"mode": "in-process"},
    )
    if figures:
        from covnet.covariance_control.plots import make_figures  # matplotlib: start-up

        make_figures(out)
    print_summary(out, summary)
    return EXIT_OK


def run_surveillance(sc: Scenario, out: Path, *, figures: bool) -> int:
    """``covnet run`` of a config with ``surveillance:``: every metric's run through the
    engine in this process; writes the run directory (:mod:`covnet.covariance_control.
    surveillance_results`) and its figures."""
    # start-up: the surveillance world and results only for configs with surveillance
    from covnet.covariance_control import drive, surveillance
    from covnet.covariance_control.surveillance_results import write_surveillance_run

    sm = surveillance.build(sc)

    def one(m: str) -> tuple[Any, float]:
        t0 = time.perf_counter()
        return drive.run(sc, m, sm).run, time.perf_counter() - t0

    metrics = list(sc.allocation.metrics)
    runs = {}
    for m, (r, seconds) in zip(metrics, map_in_forks(one, metrics), strict=True):
        runs[m] = r
        print(
            f"{m:>10}: {sc.scans} scans, {len(sm.truth_ids)} targets in {seconds:.2f} s, "
            f"{r.n_tracks_started} tracks started, search share "
            f"{100.0 * r.search_dwells.sum() / max(1, r.enabled.sum()):.1f} %"
        )
    summary = write_surveillance_run(out, sc, sm, runs, run_info={"mode": "in-process"})
    if figures:
        from covnet.covariance_control.plots import make_figures  # matplotlib: start-up

        make_figures(out)
    print_summary(out, summary)
    return EXIT_OK


def print_summary(out: Path, summary: dict[str, Any]) -> None:
    """The headline numbers of a run directory's ``summary.json``."""
    if "truth_ids" in summary:
        _print_surveillance_summary(out, summary)
        return
    if "target_ids" in summary:
        _print_targets_summary(out, summary)
        return
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
            + _gap_text(blk)
        )


def _print_surveillance_summary(out: Path, summary: dict[str, Any]) -> None:
    print(
        f"run directory: {out}  (config {summary['config_hash']}, seed {summary['seed']}, "
        f"search weight {summary['search_weight']:g}, {summary['association']})"
    )
    for m, b in summary["metrics"].items():
        ttc = b["time_to_confirm_mean"]
        print(
            f"  {m:>10}: GOSPA {b['gospa_mean']:.1f} m (mean), OSPA {b['ospa_mean']:.1f} m, "
            f"time to confirm {'-' if ttc is None else f'{ttc:.1f}'} scans, missed "
            f"{b['missed_targets']}, false tracks {b['false_tracks']}, breaks "
            f"{b['track_breaks']}, search {100 * b['search_share']:.0f} % of dwells"
        )


def _gap_text(blk: dict[str, Any]) -> str:
    """A bounded or greedy search's relative gap (``summary.json``'s ``gap_median`` and
    ``gap_worst``; null where the search reported none), and relative to the distance from
    doing nothing where the summary has it; nothing for an exact search."""
    if "gap_median" not in blk:
        return ""
    med, worst = blk.get("gap_median"), blk.get("gap_worst")
    if med is None or worst is None:
        return ", search gap not reported"
    text = f", search gap median {100 * med:.2f} %, worst {100 * worst:.2f} %"
    n_med, n_worst = blk.get("gap_nothing_median"), blk.get("gap_nothing_worst")
    if n_med is not None and n_worst is not None:
        text += (
            f" (of the distance from doing nothing: median {100 * n_med:.2f} %, "
            f"worst {100 * n_worst:.2f} %)"
        )
    return text


def _lost_text(t: dict[str, Any], cutoff_m: float | None) -> str:
    """``covnet mc``'s criterion of a lost track: ever further from the truth than the OSPA
    cut-off."""
    worst = t.get("max_position_error")
    if cutoff_m is None or worst is None or not worst > cutoff_m:
        return ""
    return f", track lost (max error {worst:.0f} m > OSPA cut-off {cutoff_m:g} m)"


def _print_targets_summary(out: Path, summary: dict[str, Any]) -> None:
    print(
        f"run directory: {out}  (config {summary['config_hash']}, seed {summary['seed']}, "
        f"fusion {summary.get('fusion', 'central')}, association {summary['association']})"
    )
    cutoff = summary.get("ospa", {}).get("cutoff_m")
    for m, blk in summary["metrics"].items():
        print(
            f"  {m:>10}: rate {100 * blk['allocation_rate']:5.1f} %, mean OSPA "
            f"{blk['mean_ospa']:.1f} m, mean GOSPA {blk['mean_gospa']:.1f} m" + _gap_text(blk)
        )
        off = {sid: n for sid, n in blk.get("required_off", {}).items() if n}
        if off:
            scans = len(blk["sensors_per_scan"])
            print(
                f"  {'':>10}  required sensors off: "
                + ", ".join(f"{sid} in {n} of {scans} scans" for sid, n in off.items())
                + " (failed, covering no target, or no room under allocation.max_per_target)"
            )
        for tid, t in blk["targets"].items():
            lo, hi = t["nees_band_95"]
            nis = "-" if t["mean_nis"] is None else f"{t['mean_nis']:.2f}"
            print(
                f"  {'':>10}  {tid}: position RMSE {t['rmse_position']:7.2f} m, mean NEES "
                f"{t['mean_nees']:6.2f} (95 % band {lo:.2f}-{hi:.2f}), mean NIS {nis}, "
                f"{sum(t['sensors_per_scan']) / max(len(t['sensors_per_scan']), 1):.2f} "
                "sensors per scan" + _lost_text(t, cutoff)
            )


def after_up(sc: Scenario, out: Path, *, figures: bool) -> None:
    """After ``covnet up``: the figures and the summary of the scans done."""
    if not (out / SUMMARY).is_file():
        return
    summary = read_json(out / SUMMARY)
    if figures and summary["metrics"]:
        from covnet.covariance_control.plots import make_figures  # matplotlib: start-up

        make_figures(out)
    print_summary(out, summary)


def up_problem(
    sc: Scenario, *, realtime: bool, netns: bool, foxglove: bool = False
) -> str | None:
    """Why ``covnet up`` cannot run ``sc`` this way (None: it can)."""
    if not sc.fusion.has_centre and realtime:
        return "--realtime: fusion.mode peer runs in lockstep only (leave out --realtime)"
    if not sc.fusion.has_centre and foxglove:
        # the visual channels draw the fusion centre's scans: a live view of a peer run
        # advertised its channels and sent nothing
        return (
            "--foxglove: fusion.mode peer has no fusion centre whose scans the visual channels "
            "draw (its recording holds the nodes' tracks and statuses, not the scenes)"
        )
    if not sc.network.latency.is_ideal(sc.sensor_ids):
        if not sc.fusion.has_centre:
            return "network.latency: peer mode has no fusion centre to be late for"
        if not realtime and not netns:
            return (
                "network.latency describes slow or lossy links: run covnet up with --realtime "
                "(a lockstep run waits for every message), or covnet run / covnet sweep, which "
                "simulate the links in simulated time"
            )
    return None


#: the batch tables whose directories have per-point curves (``covnet plot --point``)
TABLES = ("compare", "sweep")


def plot(run_dir: Path, point: str | None = None) -> list[Path]:
    """Redraw the figures of a run, ``covnet mc``, ``covnet compare`` or ``covnet sweep``
    directory: a batch's table figure and its per-scan curves (``curves.png``: the default
    points, or with ``point`` every point whose key contains it, e.g.
    ``delay_ms=350,loss=0,mode=central``)."""
    if point is not None and not any((run_dir / f"{s}.json").is_file() for s in TABLES):
        what = "covnet mc" if (run_dir / "montecarlo.json").is_file() else "run"
        raise UsageError(
            f"--point: {run_dir} is a {what} directory; per-point curves are drawn for covnet "
            "sweep and covnet compare directories"
        )
    if (run_dir / "montecarlo.json").is_file():
        from covnet.covariance_control.plots import mc_figure  # matplotlib: start-up

        return [mc_figure(run_dir)]
    for stem in TABLES:
        table = run_dir / f"{stem}.json"
        if table.is_file():
            # start-up: the table modules only for their directories
            from covnet.covariance_control import compare as compare_module
            from covnet.covariance_control import sweep as sweep_module

            module = compare_module if stem == "compare" else sweep_module
            try:
                doc = read_json(table)
                rows = doc["rows"]
            except (ValueError, KeyError) as exc:
                raise UsageError(f"{table}: not a {stem} table ({exc})") from None
            _check_trial_hash(run_dir, stem, doc)
            if doc.get("surveillance"):  # a surveillance sweep or comparison: no curves
                return [_surveillance_table_figure(run_dir, stem, rows, point)]
            if doc.get("compared") == "policies":  # covnet compare --policies
                from covnet.covariance_control import compare_policies as module
            # --point checked before anything is drawn (a refused one redrew the table's
            # figure, then exited 2)
            select: list[int] | None = None
            if (run_dir / CURVES).is_file():
                curves = load_arrays(run_dir / CURVES)
                keys = [str(k) for k in curves["points"]]
                select = (
                    module.default_curves(rows)
                    if point is None
                    else [i for i, k in enumerate(keys) if point in k]
                )
                if not select:
                    raise UsageError(
                        f"--point {point}: no point of {run_dir} matches; its points: "
                        + "; ".join(keys)
                    )
            elif point is not None:
                raise UsageError(f"--point: {run_dir} has no per-scan curves ({CURVES})")
            title = module.figure_title(doc)  # the command's own
            figures = [module.make_figure(run_dir, rows, title)]
            if select is not None:
                figures.append(module.curves_figure(run_dir, curves, select))
            return figures
    if (run_dir / "batch.json").is_file():  # a batch's directory without its table
        raise UsageError(
            f"{run_dir}: a covnet mc, sweep or compare directory without its table "
            "(montecarlo.json, sweep.json or compare.json): interrupted before the end? The "
            "same command with the same --out finishes it (its trials are kept)"
        )
    missing = [f for f in (SUMMARY, "arrays.npz") if not (run_dir / f).is_file()]
    if missing:
        raise UsageError(f"{run_dir}: not a complete run directory (missing {', '.join(missing)})")
    if not read_json(run_dir / SUMMARY).get("metrics"):
        raise UsageError(
            f"{run_dir}: no scan of this run was done ({SUMMARY} has no metric's results): "
            "there is nothing to draw"
        )
    from covnet.covariance_control.plots import make_figures  # matplotlib: start-up

    return make_figures(run_dir)


def _surveillance_table_figure(
    run_dir: Path, stem: str, rows: list[dict[str, Any]], point: str | None
) -> Path:
    """A surveillance ``sweep.png`` (over the search weight) or ``compare.png`` (policies)."""
    # start-up: the surveillance batch only for its directories
    from covnet.covariance_control import surveillance_batch as sb

    if point is not None:
        raise UsageError(
            f"--point: {run_dir} is a surveillance {stem}, whose figure shows every point; it "
            "keeps no per-point curves"
        )
    draw = sb.sweep_figure if stem == "sweep" else sb.compare_figure
    try:
        return draw(run_dir, rows)
    except (KeyError, TypeError, ValueError) as exc:
        raise UsageError(
            f"{run_dir / f'{stem}.json'}: not a surveillance {stem} table as covnet writes it "
            f"({type(exc).__name__}: {exc}); was it edited?"
        ) from None


def _check_trial_hash(run_dir: Path, stem: str, doc: dict[str, Any]) -> None:
    """A ``compare`` or ``sweep`` table's ``trial_hash`` against the one of the directory's
    ``config.json`` (edited after the batch: refused, as ``covnet plot`` refuses a run's)."""
    from covnet.covariance_control import compare as compare_module  # start-up: tables only
    from covnet.covariance_control import sweep as sweep_module

    stored = doc.get("trial_hash")
    if stored is None:
        return
    sc = from_dict(read_json(run_dir / CONFIG), str(run_dir / CONFIG))
    metric = str(doc.get("metric"))
    if stem == "sweep":
        keys = [sweep_module.trial_key(sc, metric)]
    elif doc.get("compared") == "policies":
        from covnet.covariance_control import compare_policies  # start-up: tables only

        keys = [compare_policies.trial_key(sc, metric)]
    else:  # the graph it names, or none given (the config's)
        keys = [compare_module.trial_key(sc, metric, g) for g in (None, doc.get("graph"))]
    if stored not in keys:
        raise UsageError(
            f"{run_dir / CONFIG}: not the config of this {stem}'s results ({stem}.json: trial "
            f"hash {stored}, config.json: {keys[0]}); was it edited after the {stem}? Put "
            "back the config it used"
        )


def metric_opt(sc: Scenario, requested: list[str] | None, default: str) -> str:
    """The one metric a ``--metric`` option names (repeated: the same), else ``default``; a
    known one.  Two different ones are refused: the command runs one (it took the last)."""
    names = list(dict.fromkeys(requested or [default]))
    for name in names:
        known_metric(name)
    if len(names) > 1:
        raise UsageError(
            f"--metric: this command compares with one metric, got {', '.join(names)}; run it "
            "once per metric"
        )
    return names[0]


def known_metric(metric: str) -> str:
    """``metric`` if it is registered (``--metric``'s check), else a usage error naming them."""
    if metric not in METRICS:
        raise UsageError(f"--metric: unknown metric {metric!r}; choose from {sorted(METRICS)}")
    return metric


def bench_fusion(args: argparse.Namespace, sc: Scenario | None) -> int:
    """``covnet bench fusion``: the batched covariance-intersection candidates."""
    from covnet.covariance_control import bench_fusion as bf  # start-up of the other commands

    rows = bf.run_bench(args.sensors or [8, 12, 16], repeat=args.repeat)
    if args.json:
        for row in rows:
            print(json_line(row))
    else:
        print(bf.format_table(rows))
    return EXIT_OK


def bench_search(args: argparse.Namespace, sc: Scenario | None) -> int:
    """``covnet bench search``: branch and bound, bounded and greedy against the exhaustive
    search (bit-identical where both run) and plain greedy, per metric and N."""
    from covnet.covariance_control import bench_search as bs  # start-up of the other commands

    metrics = [known_metric(m) for m in args.metric] if args.metric else None
    searches = args.search or list(bs.SEARCHES)
    for s in searches:
        if s not in bs.SEARCHES:
            raise UsageError(f"--search: unknown search {s!r}; choose from {list(bs.SEARCHES)}")
    big = [n for n in args.sensors or () if n > bs.EXACT_MAX]
    if args.search and "exact" in args.search and big:
        # exact above EXACT_MAX gave no row at all, and said nothing
        raise UsageError(
            f"--search exact: bench search runs the exact search up to {bs.EXACT_MAX} sensors, "
            f"got --sensors {big[0]} (beyond it: --search bounded or greedy)"
        )
    if not args.json:
        print(bs.header(), flush=True)
    rows = bs.run(
        args.sensors or [8, 12, 16, 20, 24, 32],
        metrics,
        searches,
        args.problems,
        args.repeat,
        exact_cap_s=bs.EXACT_CAP_S if args.exact_cap is None else args.exact_cap,
        progress=None if args.json else (lambda line: print(line, flush=True)),
        on_row=(lambda row: print(json_line(row), flush=True)) if args.json else None,
        clock=args.clock,
    )
    agree = all(r["agree_exhaustive"] in (None, True) for r in rows)
    if not agree:
        print("covnet: error: a search disagreed with the exhaustive one", file=sys.stderr)
    return EXIT_OK if agree else EXIT_FAIL


def bench_multitarget(args: argparse.Namespace, sc: Scenario | None) -> int:
    """``covnet bench multitarget``: the multi-target assignment allocator against the plain
    enumeration of every assignment (where that runs), per metric and N."""
    from covnet.covariance_control import bench_search as bs  # start-up of the other commands

    metrics = [known_metric(m) for m in args.metric] if args.metric else None
    if args.search:
        return _bench_multitarget_scale(args, metrics)
    if args.clock != "wall":
        raise UsageError(
            "--clock: bench multitarget takes it with --search (the searches at scale, whose "
            "bounded search has a time limit)"
        )
    if args.sensors and max(args.sensors) > 16:
        raise UsageError(
            "--sensors: bench multitarget takes up to 16 without --search (its sensor table); "
            "with --search exact|bounded|greedy generated networks up to 256"
        )
    targets = getattr(args, "targets", None) or [3]
    if any(not 1 <= t <= len(bs.MT_TARGETS) + len(bs.MT_MORE_TARGETS) for t in targets):
        raise UsageError(
            f"--targets: 1 to {len(bs.MT_TARGETS) + len(bs.MT_MORE_TARGETS)}, got {targets}"
        )
    if not args.json:  # after the checks: a refused command prints no table header
        print(" ".join(k for k, _ in bs.MT_COLUMNS), flush=True)
    rows = bs.run_multitarget(
        args.sensors or [8, 12, 16],
        metrics or ("spectral", "abs_trace", "svd", "kl"),
        args.problems,
        args.repeat,
        progress=None if args.json else (lambda line: print(line, flush=True)),
        target_counts=targets,
    )
    if args.json:
        for row in rows:
            print(json_line(row))
    return _agreed(rows)


def _agreed(rows: Sequence[dict[str, Any]]) -> int:
    """EXIT_OK, or EXIT_FAIL (said on stderr) when a row's check against a reference found a
    disagreement (``agree_reference``, ``exact_agree``, ``reference_agree`` False: the bench
    printed it and exited 0, where ``bench search`` and ``bench`` exit 1)."""
    keys = ("agree_reference", "exact_agree", "reference_agree")
    if any(row.get(k) is False for row in rows for k in keys):
        print("covnet: error: an allocator disagreed with its reference", file=sys.stderr)
        return EXIT_FAIL
    return EXIT_OK


def _bench_multitarget_scale(args: argparse.Namespace, metrics: list[str] | None) -> int:
    """``covnet bench multitarget --search ...``: the searches at scale
    (:mod:`covnet.covariance_control.bench_multitarget`)."""
    from covnet.covariance_control import bench_multitarget as bm  # start-up of the others

    targets = getattr(args, "targets", None) or [3, 8, 16]
    bad = [s for s in args.search if s not in bm.SEARCH_NAMES]
    if bad:
        raise UsageError(f"--search: one of {', '.join(bm.SEARCH_NAMES)}, got {bad[0]!r}")
    if any(t < 1 for t in targets):
        raise UsageError(f"--targets: at least 1, got {targets}")
    cols = (
        *("metric", "n_sensors", "n_targets", "search", "median_s", "gap_median"),
        *("gap_nothing_median", "n_exact", "ratio_greedy", "excess_exact", "reference_agree"),
        *("meets_time", "meets_gap", "meets_gap_nothing"),
    )

    def show(row: dict[str, Any]) -> None:
        if args.json:
            print(json_line(row), flush=True)
        else:
            keys = cols[:4] + ("skipped",) if row.get("skipped") else cols
            print(" ".join(f"{k}={row[k]:.4g}" if isinstance(row[k], float) else f"{k}={row[k]}"
                           for k in keys), flush=True)  # fmt: skip

    rows = bm.run(
        args.sensors or [16, 64, 256],
        targets,
        metrics or ("kl", "spectral", "abs_trace"),
        args.search,
        args.problems,
        args.repeat,
        progress=show,
        clock=args.clock,
    )
    return _agreed(rows)


def bench_alloc(args: argparse.Namespace, sc: Scenario | None) -> int:
    """``covnet bench [alloc]``: allocation decisions per metric and N against the plain loop."""
    from covnet.covariance_control import bench_allocation  # start-up of the other commands

    sensors = args.sensors or [8, 12, 16, 20]
    sc = sc if sc is not None else load(args.config)
    metrics = [metric_opt(sc, [m], m) for m in args.metric] if args.metric else None
    other = [s.id for s in sc.sensors if s.sigma_x_m is None or s.sigma_y_m is None]
    if other:  # (it was taken for a 1 m position sensor)
        raise UsageError(
            f"--config: the allocator bench takes position sensors (sigma_x_m, sigma_y_m); "
            f"{other[0]} is not one"
        )
    table = [s.position_noise for s in sc.sensors]
    if len(table) < 8 and max(sensors) > len(table):  # (a traceback at the first size)
        raise UsageError(
            f"--sensors {max(sensors)}: beyond the config's {len(table)} sensors the bench "
            "repeats its first 8, scaled: give a config of 8 or more, or --sensors up to "
            f"{len(table)}"
        )

    def progress(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    rows = bench_allocation.run(
        table,
        sensors,
        metrics,
        n_problems=args.problems,
        repeat=args.repeat,
        progress=None if args.json else progress,
    )
    if args.json:
        keys = ("metric", "n_sensors", "median_s", "baseline_median_s", "peak_mb")
        for row in rows:
            print(json_line({k: row[k] for k in keys} | {"agree": row["agree"]}))
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
