"""The ``covnet`` commands but ``bench`` (:mod:`covnet.cli.bench_commands`): ``run``,
``mc``, ``compare``, ``sweep``, ``replay``, ``up``, ``check`` and ``plot``, each a
``cmd_NAME(args) -> int`` that :func:`covnet.cli.app.build_parser` binds to its subcommand.

None knows a scenario kind: each loads the config through :mod:`covnet.kinds` and calls what
the kind provides."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from covnet import kinds
from covnet.cli.common import (
    EXIT_FAIL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    RUN_OPTIONS,
    _err,
    _load,
    _note,
    _options,
)
from covnet.config import endpoint_problem, endpoint_security_problem, hash_of, read_yaml
from covnet.errors import UpError, UsageError
from covnet.processes import interrupts
from covnet.runs.rundir import (
    CONFIG,
    RUN_INFO,
    after_the_results,
    check_writable,
    config_mismatch,
    prepare_out,
    read_json,
    record_end,
    run_info,
)


def cmd_run(args: argparse.Namespace) -> int:
    """``covnet run``: the results are written once, when every scan is done (then
    ``run.json`` says ``completed``), the figures after them; a Ctrl-C before the results
    leaves nothing, one while drawing leaves the complete results."""
    kind, cfg = _load(args, *RUN_OPTIONS)
    problem = kind.mcap_problem(cfg) if args.mcap else None
    if problem is not None:  # before the run: it was refused after it, with a run.mcap begun
        raise UsageError(f"--mcap: {problem}")
    out = prepare_out(args.out, cfg.name, args.force)
    try:
        status = int(kind.run(cfg, out, figures=not args.no_figures))
        if status == EXIT_OK and args.mcap:
            # start-up: the Foxglove SDK and the visual channels only for --mcap
            from covnet.runs.visual import write_run_mcap

            print(f"visual channels for Foxglove: {write_run_mcap(kind, cfg, out)}")
        if status == EXIT_OK:  # (in the try: a Ctrl-C just before it is answered below)
            record_end(out, "completed", "every scan done")
    except BaseException as exc:
        # every kind writes run.json last: with it the results are whole (it was written before
        # summary.json, and a Ctrl-C between them was recorded as complete)
        whole = (out / RUN_INFO).is_file()
        if isinstance(exc, BrokenPipeError) and whole:  # covnet run | head: results whole
            record_end(out, "completed", "every scan done (its printed output cut)")
        if not interrupts.caused(exc):
            raise
        # a Ctrl-C held while run.json was written (interrupts.held): its status is said
        if whole and run_info(out).get("status") == "completed":
            _note(f"interrupted as it ended: {out} holds the complete results")
        elif whole:
            later = "figures" if not args.no_figures else "printing"
            record_end(out, "completed", f"every scan done ({later} interrupted)")
            _note(f"interrupted after the results were written: {out} holds the complete "
                  f"results (covnet plot {out} draws the figures)")  # fmt: skip
        elif out.is_dir() and any(out.iterdir()):
            record_end(out, "interrupted", "while the results were written: incomplete")
            _note(f"interrupted while the results were written: {out} is incomplete")
        else:
            _note("interrupted before the results were written: nothing written")
        raise
    return status


def cmd_mc(args: argparse.Namespace) -> int:
    kind, cfg = kinds.load(args.config)
    names = ("seed", "metric", "fusion")
    takes = getattr(kind, "mc_options", None)  # optional: fewer than the kind's run options
    cfg = kinds.apply_options(
        kind,
        cfg,
        args.config,
        taken=names if takes is None else [n for n in names if n in takes],
        **_options(args, *names),
    )
    return kinds.command(kind, "mc", "a Monte Carlo protocol")(args, cfg)


def cmd_compare(args: argparse.Namespace) -> int:
    kind, cfg = _load(args, "seed")
    return kinds.command(kind, "compare", "comparing fusion structures")(args, cfg)


def cmd_sweep(args: argparse.Namespace) -> int:
    kind, cfg = _load(args, "seed")
    return kinds.command(kind, "sweep", "the network-latency sweep")(args, cfg)


def cmd_replay(args: argparse.Namespace) -> int:
    run_dir = Path(args.run_dir)
    _replayable(run_dir)  # a run stopped before its first scan may have no config.json
    if not (run_dir / CONFIG).is_file():
        raise UsageError(f"{run_dir}: not a recorded network run directory (no {CONFIG})")
    try:
        data = read_json(run_dir / CONFIG)
    except ValueError as exc:
        raise UsageError(f"{run_dir / CONFIG}: not valid JSON ({exc})") from None
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
    if args.speed is not None and not (math.isfinite(args.speed) and args.speed > 0):
        # inf made every period 0: the manager failed before READY
        raise UsageError(f"--speed: must be a finite number > 0, got {args.speed}")
    if args.router is not None and (
        (problem := endpoint_problem(args.router)) is not None
        or (problem := endpoint_security_problem(args.router, cfg.network)) is not None
    ):
        raise UsageError(f"--router: {problem}")
    k = args.sensors_per_process
    if k is not None and k < 1:
        raise UsageError(f"--sensors-per-process: must be >= 1, got {k}")
    if k not in (None, 1) and args.netns:
        raise UsageError("--sensors-per-process: --netns runs each sensor in its own namespace")
    problem = kind.up_problem(
        cfg, realtime=args.realtime, netns=args.netns, foxglove=bool(args.foxglove)
    )
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
        if args.foxglove:  # (it told the user to open an address nothing on the host served)
            raise UsageError(
                "--foxglove: with --netns the live view's server runs inside the manager's "
                "network namespace, out of the host's reach; leave out one of them (the "
                "recording holds the same channels: open recording.mcap in Foxglove after)"
            )
        reason = unsupported_reason()
        if reason is not None:
            raise UsageError(reason)
    if args.nodes is not None and not args.nodes.strip():
        raise UsageError("--nodes: empty; name the processes to start here (e.g. sensors)")
    nodes = [n.strip() for n in args.nodes.split(",")] if args.nodes else None
    known = {"manager", "world", "recorder", "sensors", *cfg.sensor_ids}
    for n in nodes or []:
        if n not in known:
            raise UsageError(f"--nodes: unknown process {n!r}; choose from {sorted(known)}")
        if n == "recorder" and not cfg.network.record:  # (it started nothing and exited 0)
            raise UsageError(
                "--nodes recorder: network.record is false in the config, so no recorder runs"
            )
    router = args.router or cfg.network.router
    if (
        nodes is not None
        and "manager" not in nodes
        and cfg.network.connect is None
        and router.rpartition(":")[2] == "0"  # a free port of this host, where nothing listens
    ):
        raise UsageError(
            f"--nodes {args.nodes}: the manager (the network's router) runs elsewhere, so "
            "these nodes connect to it: give --router with its endpoint and port (e.g. "
            "tcp/192.0.2.10:7447), or network.router or network.connect in the config (port "
            "0 picks a free port, known only on the manager's host)"
        )
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
    # interrupted (Ctrl-C, SIGTERM, a hang-up): the summary of the scans done, not the figures,
    # which took seconds more (10 s under load) after the stop was asked for
    figures = not args.no_figures and status != EXIT_INTERRUPTED
    # the run has ended and run.json says how: a Ctrl-C while drawing keeps it and says so
    with after_the_results(out, "figures" if figures else "printing"):
        kind.after_up(cfg, out, figures=figures)
    if status == EXIT_INTERRUPTED and not args.no_figures and (out / CONFIG).is_file():
        _note(f"the figures were not drawn (interrupted): covnet plot {out} draws them")
    return status


def cmd_check(args: argparse.Namespace) -> int:
    import yaml  # the check's printout only (start-up time of the other commands)

    from covnet.wire.messages import RECORDER_ID, RESERVED_IDS  # start-up: the check's own
    from covnet.wire.security import preflight

    kind, cfg = kinds.load(args.config)
    data = kind.normalised(cfg)
    # the files security needs on this host (keys, certificates, passwords), for every node
    # the network runs (no recorder with network.record false: check asked for its password)
    nodes = [n for n in RESERVED_IDS if n != RECORDER_ID or cfg.network.record]
    preflight(cfg, [*nodes, *cfg.sensor_ids], args.config)
    print(yaml.safe_dump(data, sort_keys=False), end="")
    print(f"# config hash: {hash_of(data)}")
    for note in kind.check_notes(cfg):  # valid, but a command of the kind would refuse it
        _note(note)
    return EXIT_OK


def cmd_plot(args: argparse.Namespace) -> int:
    run_dir = Path(args.run_dir)
    if not (run_dir / CONFIG).is_file():
        raise UsageError(
            f"{run_dir}: not a complete run directory (missing {CONFIG}, which names its kind)"
        )
    # a corrupt config.json is a ConfigError (exit 2), as for replay
    kind, cfg = kinds.from_dict(read_yaml(run_dir / CONFIG), str(run_dir / CONFIG))
    stale = config_mismatch(run_dir, kinds.config_hashes(cfg))
    if stale is not None:
        raise UsageError(stale)
    # the figures go into the directory: one on a read-only file system is named now (exit 2),
    # not by the first figure's OSError
    check_writable(run_dir, f"{run_dir} (covnet plot draws the figures into it)")
    try:
        if args.point is not None:
            try:
                figures = kind.plot(run_dir, point=args.point)  # type: ignore[call-arg]
            except TypeError as exc:  # a kind whose plot takes no point
                if "point" not in str(exc):
                    raise
                raise UsageError(
                    f"--point: a {kind.title} directory has no per-point curves"
                ) from None
        else:
            figures = kind.plot(run_dir)
    except (KeyError, TypeError, AttributeError, IndexError, ValueError) as exc:
        # a result table whose layout is not the one covnet wrote (a key gone, a list where a
        # table was, null, text where a number was): edited or damaged, the user's input
        raise UsageError(
            f"{run_dir}: a result file does not have the layout covnet writes "
            f"({type(exc).__name__}: {exc}); was it edited? The command that made the "
            "directory writes it again"
        ) from None
    for p in figures:
        print(p)
    return EXIT_OK


def cmd_export(args: argparse.Namespace) -> int:
    """``covnet export RUN --format csv|stonesoup``: a run's truths and tracks."""
    # start-up: the export's readers and writers for this command only
    from covnet.runs.export import export

    path = export(args.run_dir, args.format, args.out, args.episode, args.force)
    if path is not None:
        print(path)
    return EXIT_OK
