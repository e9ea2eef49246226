"""The ``covnet`` command line: argparse, and the kind registry for everything else.

``main(argv) -> int`` so tests call it directly.  Exit status: 0 success, 1 a run failed,
2 a user's mistake (bad config, bad option, an existing run directory), 130 interrupted.
A user's mistake prints one readable message to stderr, never a traceback.

No command here knows a scenario kind: each loads the config through :mod:`covnet.kinds`
(which decides the kind once) and calls what the kind provides; a command a kind does not
have, or an option it does not take, is refused with a line that says so.

This module holds :func:`main` and the parser (:func:`build_parser`: every subcommand, its
options and its ``cmd_NAME``); the commands are in :mod:`covnet.cli.commands` and
:mod:`covnet.cli.bench_commands`, what they share in :mod:`covnet.cli.common`.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import covnet.errors  # noqa: F401  (first: a folder named covnet/ taken for it says so)

# isort: split
from covnet import __version__
from covnet.batches import MAX_SEEDS
from covnet.cli.bench_commands import (
    BENCH_DEFAULTS,
    BENCH_SENSORS_MAX,
    BENCH_TAKES,
    BENCHES,
    cmd_bench,
    cmd_bench_up,
)
from covnet.cli.commands import (
    cmd_check,
    cmd_compare,
    cmd_export,
    cmd_mc,
    cmd_plot,
    cmd_replay,
    cmd_run,
    cmd_sweep,
    cmd_up,
)
from covnet.cli.common import (
    EXIT_FAIL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_PIPE,
    EXIT_USAGE,
    RUN_OPTIONS,
    _err,
)
from covnet.config import ConfigError, ConfigWarning, config_warnings_once, scheduler_problem
from covnet.errors import ClusterLost, UpError, UsageError, WorkerDied
from covnet.processes import interrupts, output
from covnet.runs import rundir

__all__ = [
    "BENCHES",
    "BENCH_DEFAULTS",
    "BENCH_SENSORS_MAX",
    "BENCH_TAKES",
    "EXIT_FAIL",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_PIPE",
    "EXIT_USAGE",
    "RUN_OPTIONS",
    "build_parser",
    "cmd_bench",
    "cmd_bench_up",
    "cmd_check",
    "cmd_compare",
    "cmd_export",
    "cmd_mc",
    "cmd_plot",
    "cmd_replay",
    "cmd_run",
    "cmd_sweep",
    "cmd_up",
    "main",
]


def _counts(what: str) -> Callable[[str], list[int]]:
    """The parser of a comma-separated list of ``what`` counts (sensor, target), each >= 1."""

    def parse(text: str) -> list[int]:
        try:
            vals = [int(v) for v in text.split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected comma-separated integers, got {text!r}"
            ) from None
        if not vals or any(v < 1 for v in vals):
            raise argparse.ArgumentTypeError(f"{what} counts must be >= 1, got {text!r}")
        if len(set(vals)) < len(vals):  # "8,8" timed the same size twice, two rows
            raise argparse.ArgumentTypeError(f"a count given twice in {text!r}")
        return vals  # each benchmark's largest count: BENCH_SENSORS_MAX, checked in cmd_bench

    return parse


def _seed_count(text: str) -> int:
    """``--trials``, ``--seeds``, ``--runs``, ``--max-seeds``: an integer, at most
    :data:`MAX_SEEDS` (each command checks its own least value and says why)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if n > MAX_SEEDS:
        raise argparse.ArgumentTypeError(f"at most {MAX_SEEDS} in one batch, got {n}")
    return n


class _OneOf(argparse.Action):
    """An option with an alias (``--runs`` / ``--seeds``, ``--trials`` / ``--seeds``): given
    twice it is refused; argparse took the last one without a word (``--runs 2 --seeds 3``
    ran 3)."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        mark = f"_given_{self.dest}"
        first = getattr(namespace, mark, None)
        if first is not None:
            parser.error(f"{first} and {option_string}: one option given twice; give it once")
        setattr(namespace, mark, option_string)
        setattr(namespace, self.dest, values)


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
        type=_seed_count,
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
        "--seeds",
        dest="trials",
        action=_OneOf,
        type=_seed_count,
        metavar="N",
        help="seeds (covariance control: from the config's, default 20; mobile: 0..N-1, "
        "default 20) or trials per cell (passive, default: config); --seeds is the same "
        "option, named as sweep's",
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
        help="fusion structures (--modes) or allocation policies (--policies) side by side "
        "over a Monte Carlo batch",
    )
    cp.add_argument("config", help="scenario YAML, e.g. configs/paper.yaml")
    what = cp.add_mutually_exclusive_group()
    what.add_argument(
        "--modes",
        help="comma-separated fusion structures: a fusion rule at a centre (central, info, ci), "
        "ci-fast, or peer-<rule> (peer-info, peer-ci); default: all but ci-fast",
    )
    what.add_argument(
        "--policies",
        help="comma-separated allocation policies (allocation.policy): covariance_control, "
        "all_on, random, round_robin, greedy_information, uncertainty_reward, expected_kl; "
        "one target or targets:, the same seeds for each; writes compare.json, pareto.png, "
        "curves.png",
    )
    cp.add_argument(
        "--budget",
        metavar="K|match",
        help="with --policies: K sensors per scan for every policy that takes a budget; "
        "'match': K = covariance control's mean sensors per scan (run first); default: the "
        "config's allocation.budget",
    )
    cp.add_argument(
        "--runs",
        "--seeds",
        dest="runs",
        action=_OneOf,
        type=_seed_count,
        default=20,
        help="seeds per mode or policy (default: %(default)s); --seeds is the same option, "
        "named as sweep's",
    )
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
    cp.add_argument(
        "--no-figures",
        action="store_true",
        help="skip compare.png (--policies: pareto.png and curves.png)",
    )
    cp.add_argument(
        "--json",
        action="store_true",
        help="JSON Lines on stdout: one JSON object per line, a row per mode or policy",
    )
    cp.set_defaults(func=cmd_compare)

    sw = sub.add_parser(
        "sweep",
        help="network latency: a grid of delay x loss x fusion mode x seeds (the config's sweep)",
    )
    sw.add_argument("config", help="scenario YAML with a sweep section, e.g. configs/latency.yaml")
    sw.add_argument("--seeds", type=_seed_count, help="seeds per grid point (default: sweep.seeds)")
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
        "and Track objects in Stone Soup's YAML (needs: pip install 'covnet[stonesoup]'). "
        "A peer run's track is one node's estimate, the one summary.json's metrics block "
        "holds (the first sensor's, S1 in the shipped configs; covnet up: the first of those "
        "that reported the most scans); every node's own are arrays.npz's "
        "x_est.<metric>.<node>.",
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
    ex.add_argument(
        "--force", action="store_true", help="replace an existing --out file (not a run's own)"
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
        type=_counts("sensor"),
        metavar="N,N,...",
        help=takes("sensors") + "sensor counts (default 8,12,16,20; fusion: 8,12,16; search: "
        "8,...,32; beyond 8 the paper table cycles with both sigmas scaled by 1 + 0.5 (j // 8)); "
        "at most 24 for alloc and fusion, 16 for multitarget (256 with --search)",
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
        "--clock",
        choices=["wall", "cpu"],
        help=takes("clock") + "what the decisions are timed by and their limits count: the "
        "wall clock (default), or the process's CPU time, which other processes' load does "
        "not eat into (multitarget: with --search)",
    )
    b.add_argument(
        "--targets",
        type=_counts("target"),
        metavar="T,T,...",
        help=takes("targets") + "numbers of targets (default 3, the spec's scenario; up to 8; "
        "multitarget --search: default 3,8,16, any)",
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
        help=takes("repeat") + "timed repeats per problem (alloc, fusion: default 3), whole runs "
        "(up), alternations (cluster, default 4, at least 2)",
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
        "--steady",
        action="store_true",
        help=takes("steady") + "with --sensors: the CPU a scan in the steady middle of long runs, "
        "covnet's by role against the probe's, and the budget one half of the probe leaves",
    )
    b.add_argument(
        "--sensors-per-process",
        type=int,
        metavar="K",
        help=takes("sensors_per_process") + "sensors per sensor process, with --sensors (default: "
        "covnet up's)",
    )
    b.add_argument(
        "--scans",
        type=int,
        help=takes("scans") + "lockstep scans (soak: 0 none, default 20000; up --steady: each "
        "steady run's, default 3000)",
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
    b.add_argument(
        "--work",
        help=takes("work") + "keep the soak's run directories here (a new or empty directory)",
    )
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
    _host_showwarning(message, category, filename, lineno, file, line)


_host_showwarning = warnings.showwarning
#: the commands running now that use :func:`_show_warning` (threads of one process: the last
#: one to end puts the host's back, whatever their order)
_showing = 0
_showing_lock = threading.Lock()


@contextlib.contextmanager
def _the_hosts_state_kept() -> Iterator[None]:
    """Around a command: the SIGINT/SIGTERM/SIGHUP handlers (main thread), the unraisable hook
    and ``warnings.showwarning`` the command installs are the process's as it found them once
    it returns, and an interruption it asked for is over (:func:`interrupts.end_command`).
    A program calling :func:`main` kept covnet's: a SIGTERM or hang-up raised
    ``KeyboardInterrupt`` in it instead of ending it, and after an interrupted command its own
    unraisable errors (a ``__del__``'s) were dropped.  The console script's own handlers, put
    in place before this, stay."""
    global _showing, _host_showwarning
    signals = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    in_main = threading.current_thread() is threading.main_thread()
    handlers = {s: signal.getsignal(s) for s in signals} if in_main else {}
    hook = sys.unraisablehook
    with _showing_lock:
        if _showing == 0 and warnings.showwarning is not _show_warning:
            _host_showwarning = warnings.showwarning
        _showing += 1
        warnings.showwarning = _show_warning
    try:
        yield
    finally:
        with _showing_lock:
            _showing -= 1
            if _showing == 0 and warnings.showwarning is _show_warning:
                warnings.showwarning = _host_showwarning
        if in_main:
            for signum, handler in handlers.items():
                if handler is not None:  # (None: one not installed from Python; left as is)
                    signal.signal(signum, handler)
            sys.unraisablehook = hook
            if not getattr(hook, "covnet_interrupts", False):  # not the console script's
                interrupts.end_command()


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
    except (OSError, ValueError, AttributeError):
        return False
    output.silence()
    return True


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command ``argv`` (default: ``sys.argv[1:]``) and return its exit status; a
    program may call it, also from a thread: the process's signal handlers, unraisable hook
    and ``warnings.showwarning`` are as it found them once it returns."""
    with _the_hosts_state_kept():
        return _command(argv)


def _command(argv: Sequence[str] | None) -> int:
    if threading.current_thread() is threading.main_thread():
        # SIGINT and SIGTERM raise KeyboardInterrupt; one inside a weakref callback is raised
        # again, not printed and lost
        interrupts.deliver_late_interrupts()
    interrupts.begin_command()
    output.reset()
    parser = build_parser()
    args = parser.parse_args(argv)
    # the config a command reads: --force never empties a directory holding it
    config = getattr(args, "config", None)
    try:
        # the output directories the command claims (prepare_out) are released when it ends
        reads = [config] if isinstance(config, str) and config else []
        with rundir.claims(), rundir.reading(*reads), config_warnings_once():
            status = int(args.func(args))
        # the output still buffered is written here, where a reader that has gone is told
        # from a failure (not at the interpreter's exit: "Exception ignored", status 120)
        sys.stdout.flush()
        if output.gone() and status == EXIT_OK:  # a reader gone while it worked on (up)
            return EXIT_PIPE
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
    except (WorkerDied, ClusterLost) as exc:  # a batch's worker or scheduler gone: not a bug
        _err("; ".join([str(exc), *getattr(exc, "__notes__", ())]))
        return EXIT_FAIL
    except BrokenPipeError:
        if not _stdout_closed():
            raise
        return EXIT_PIPE
    except OSError as exc:  # a file covnet reads or writes: a directory in its place, no room
        # (the writers name their file; a note: run.json could not record the failure either)
        _err("; ".join([rundir.os_error_text(exc), *getattr(exc, "__notes__", ())]))
        return EXIT_FAIL
    except BaseException as exc:  # a Ctrl-C, or an extension's stand-in for one it swallowed
        if not interrupts.caused(exc):
            why = _numerical_failure(exc)
            if why is None:
                raise
            _err(why)
            return EXIT_FAIL
        interrupts.answered()
        _err("interrupted")
        return EXIT_INTERRUPTED


def _numerical_failure(exc: BaseException) -> str | None:
    """The message for a covariance that lost positive definiteness in a run (numpy's
    ``LinAlgError``, the allocator's :class:`NotPositiveDefinite`), else None.  A config whose
    scales are far apart (a period of 1e14 s, process noise of 1e14) reaches it within double
    precision; it ended in a traceback."""
    # start-up: numpy and the allocator only on a failure
    import numpy as np

    from covnet.core.allocation.exact import NotPositiveDefinite

    if not isinstance(exc, np.linalg.LinAlgError | NotPositiveDefinite):
        return None
    return (
        f"numerical failure: {exc}\n  the config's scales (periods, noise levels, initial "
        "and desired covariances) may be too far apart for double precision; if they are "
        "sensible, this is a bug in covnet: please report it with the config"
    )


if __name__ == "__main__":
    sys.exit(main())
