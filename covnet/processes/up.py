"""``covnet up``: start the whole network on this machine, show its status, stop it cleanly.

Processes (each its own ``python -m``, its own zenoh session)::

    manager  (router, listens on network.router)  <-- world, S1 ... Sn (clients)

The launcher itself holds no zenoh session: it supervises the children
(:class:`covnet.processes.launch.Supervisor`: ``processes.json`` written as soon as they start;
SIGINT,
then SIGTERM, then SIGKILL on the way out), waits for the manager's ``READY`` line, renders the
manager's ``STATUS`` lines as a live display (plain lines when not on a terminal), restarts
sensors under ``network.restart: on-failure``, and, once the manager is done, stops the rest and
draws the figures from the run directory.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from covnet.code_identity import packages_root
from covnet.errors import UpError
from covnet.processes import interrupts, output
from covnet.processes.launch import EXIT_NO_RUN, EXIT_RUN_FAILED, ProcessSpec, Supervisor
from covnet.processes.netns_launch import NetnsTopology, up_in_namespaces
from covnet.processes.node_kit import NOTE
from covnet.processes.process import run_option_args
from covnet.runs.rundir import (
    LIVE,
    RUN_INFO,
    STATUSES,
    os_error_text,
    record_end,
    try_record_end,
    write_json,
)
from covnet.runs.rundir import run_info as _run_info  # (settle's run_info: the run's facts)
from covnet.wire.security import endpoint, preflight

__all__ = [
    "HOST_PREFIX",
    "StatusView",
    "UpError",
    "default_sensors_per_process",
    "free_port",
    "hosted_by",
    "node_env",
    "process_specs",
    "resolve_router",
    "sensor_hosts",
    "up",
]

#: what node processes import, loaded once here and shared by forking (covnet.processes.forked): the
#: launcher's own imports (numpy, the kind's config) are most of the rest
NODE_PRELOAD = (
    "zenoh",
    "covnet.processes.process",
    "covnet.wire.zenoh_bus",
    "covnet.runs.recording",
    "covnet.runs.visual",
    "covnet.runs.live",
    "recorder.node",
    "sensors.host",
)
READY_GRACE_S = 15.0  # on top of network.ready_timeout_s: interpreter start-up, imports
#: on top of that, per sensor: a large network's interpreters start on few cores
READY_GRACE_PER_SENSOR_S = 0.25
#: networks of at most this many sensors get one process per sensor by default
ONE_PER_PROCESS_MAX = 16
#: a process that hosts several sensors is named ``sensors@<i>`` ('@' is not allowed in a
#: sensor id, so the name is never one)
HOST_PREFIX = "sensors@"
#: the nodes without which a run is not complete, and what is missing once one has died
VITAL = {
    "world": "no truth was published after that (the sensors measured what they had)",
    "recorder": "the recording stops there (a SIGKILL loses up to its last second of messages, "
    "the chunk it was writing), so covnet replay cannot reproduce the run",
}


def default_sensors_per_process(n_sensors: int, cores: int | None = None) -> int:
    """``covnet up``'s default ``--sensors-per-process``: 1 for at most ``ONE_PER_PROCESS_MAX``
    sensors, else as many as gives about two sensor processes per core."""
    if n_sensors <= ONE_PER_PROCESS_MAX:
        return 1
    cores = cores or os.cpu_count() or 1
    return max(1, -(-n_sensors // (2 * cores)))


def sensor_hosts(sensor_ids: Sequence[str], per_process: int) -> list[tuple[str, list[str]]]:
    """The sensor processes: ``(process name, hosted sensor ids)``, the ids in config order in
    groups of ``per_process``; a process of one sensor is named after it, a host of several
    ``sensors@1``, ``sensors@2``, ..."""
    if per_process < 1:
        raise ValueError(f"sensors per process must be >= 1, got {per_process}")
    groups = [list(sensor_ids[i : i + per_process]) for i in range(0, len(sensor_ids), per_process)]
    if per_process == 1:
        return [(g[0], g) for g in groups]
    return [(f"{HOST_PREFIX}{i + 1}", g) for i, g in enumerate(groups)]


def hosted_by(groups: Sequence[tuple[str, list[str]]]) -> dict[str, str]:
    """Sensor id -> the host process (``sensors@<i>``) that runs it, for every sensor a host
    runs; a sensor in its own process (named after it) is not listed.  (A host left with one
    sensor, the last of ``N`` by ``K`` with ``N mod K = 1``, is a host too: its sensor was left
    out of ``processes.json`` and of the certificates checked before the start.)"""
    return {sid: name for name, hosted in groups if name.startswith(HOST_PREFIX) for sid in hosted}


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def router_in_use(endpoint: str) -> str | None:
    """Why the manager could not listen on ``endpoint`` because something already does
    (another run given the same ``--router``), else None: a probe bind, before any node
    starts.  The manager found out only ~2 s later, as it opened its router, and by then this
    launcher's world and sensors had joined the other run on that port (its sensors took their
    truths, its estimate drifted, and it waited ``scan_timeout_s`` every scan).  Other bind
    errors (an address not on this host) are the manager's to report, as before."""
    proto, _, hostport = endpoint.partition("/")
    host, _, port = hostport.rpartition(":")
    if proto not in ("tcp", "tls") or not port.isdigit() or int(port) == 0:
        return None
    host = host.strip("[]")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # not fooled by TIME_WAIT
        try:
            s.bind((host, int(port)))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return (
                    f"{endpoint} is in use: something listens there already (another run "
                    "given the same --router?); its nodes would have joined that run"
                )
    return None


def resolve_router(endpoint: str) -> str:
    """``tcp/127.0.0.1:0`` -> the same with a free port; a concrete port is kept."""
    proto, _, hostport = endpoint.partition("/")
    host, _, port = hostport.rpartition(":")
    if port == "0":
        return f"{proto}/{host}:{free_port(host.strip('[]'))}"
    return endpoint


def node_env() -> dict[str, str]:
    """The environment a node process gets on top of the launcher's: ``PYTHONSAFEPATH=1``
    (Python >= 3.11's ``-P``), so ``python -m sensors`` (``manager``, ``world``, ``recorder``)
    runs covnet's node, not a ``sensors.py`` (or such a package) in the working directory,
    which ``python -m`` would put first on ``sys.path``.  Run from covnet's own folder without
    an install (``python -m covnet`` found there), that folder is what the nodes' packages
    were found by: it goes first on their ``PYTHONPATH`` instead."""
    env = {"PYTHONSAFEPATH": "1"}
    root = packages_root()
    try:
        here = Path.cwd().resolve()
    except OSError:  # a working directory deleted meanwhile: nothing to find there
        return env
    if here == root:
        env["PYTHONPATH"] = os.pathsep.join(
            p for p in (str(root), os.environ.get("PYTHONPATH", "")) if p
        )
    return env


def process_specs(
    kind: Any,
    cfg: Any,
    config_path: str,
    run_id: str,
    router: str,
    out: Path,
    *,
    options: dict[str, Any],
    realtime: bool,
    speed: float,
    sensors_per_process: int = 1,
    sensor_ids: Sequence[str] | None = None,
    foxglove: str | None = None,
) -> list[ProcessSpec]:
    """The processes of one network of any kind: ``python -m manager``, ``world``,
    ``recorder`` (when the run is recorded) and the ``sensors`` processes, each given the
    config, the run id and the same run ``options`` (so every process holds the same config).
    The sensors (``sensor_ids``, default all, in config order) go ``sensors_per_process`` to a
    process (:func:`sensor_hosts`).  ``foxglove``: ``HOST:PORT`` on which the recorder also
    serves the visual channels live (:mod:`covnet.runs.live`)."""
    py = sys.executable
    common = ["--config", str(config_path), "--run", run_id, *run_option_args(options)]
    if realtime:
        common += ["--realtime", "--speed", str(speed)]
    connect = endpoint(cfg.network, cfg.network.connect or router)
    roles = kind.restartable(cfg) if cfg.network.restart == "on-failure" else frozenset()
    env = node_env()
    specs = [
        ProcessSpec(
            "manager",
            [py, "-m", "manager", *common, "--listen", router, "--out", str(out)],
            env=env,
        ),
        ProcessSpec(
            "world",
            [py, "-m", "world", *common, "--connect", connect],
            env=env,
            restart="world" in roles,
        ),
    ]
    if cfg.network.record:
        recording = str(out / "recording.mcap")
        argv = [py, "-m", "recorder", *common, "--connect", connect, "--out", recording]
        if foxglove is not None:
            argv += ["--foxglove", foxglove]
        specs.append(ProcessSpec("recorder", argv, env=env, restart="recorder" in roles))
    ids = list(cfg.sensor_ids if sensor_ids is None else sensor_ids)
    for name, hosted in sensor_hosts(ids, sensors_per_process):
        argv = [py, "-m", "sensors", *common]
        for sid in hosted:
            argv += ["--id", sid]
        specs.append(
            ProcessSpec(name, [*argv, "--connect", connect], env=env, restart="sensor" in roles)
        )
    return specs


@dataclass
class StatusView:
    """Renders the manager's STATUS lines: a rich live bar on a terminal, plain lines else."""

    scans: int
    metrics: list[str]
    tty: bool = field(default_factory=lambda: sys.stdout.isatty())
    width: int = field(default_factory=lambda: shutil.get_terminal_size((80, 24)).columns)
    last: dict[str, Any] | None = None
    _progress: Any = None
    _task: Any = None
    _last_plain: float = 0.0

    def __enter__(self) -> StatusView:
        if self.tty:
            # rich only for a terminal (start-up time of the plain-lines case)
            from rich.progress import BarColumn, Progress, TextColumn

            self._progress = Progress(
                TextColumn("[bold]{task.fields[metric]}"),
                BarColumn(bar_width=10),
                TextColumn("{task.fields[info]}"),
                transient=False,
            )
            self.width = self._progress.console.width
            self._progress.__enter__()
            self._task = self._progress.add_task(
                "scan", total=self.scans * len(self.metrics), metric="", info="waiting for READY"
            )
        return self

    def __exit__(self, *exc: object) -> None:
        if self._progress is not None:
            self._progress.__exit__(None, None, None)

    def line(self, text: str) -> None:
        if self._progress is not None:
            self._progress.console.print(text, markup=False, highlight=False)
        else:
            output.say(text)  # (a reader gone: silence, not a traceback from this thread)

    def update(self, st: dict[str, Any]) -> None:
        """One manager STATUS line (:func:`manager.loop.run_scans`: the kind's ``info`` and the
        skeleton's counts)."""
        self.last = st
        done = st["episode"] * st["scans"] + st["scan"]
        if self._progress is not None:
            info = status_text(st, self.width - len(st["metric"]) - 12)
            self._progress.update(self._task, completed=done, metric=st["metric"], info=info)
        else:
            now = time.monotonic()
            if now - self._last_plain >= 1.0 or st["scan"] == st["scans"]:
                head = f"[status] {st['metric']}: "
                output.say(head + status_text(st, self.width - len(head)))
                self._last_plain = now


def status_text(st: dict[str, Any], width: int) -> str:
    """A manager STATUS as one line of at most ``width`` characters, abbreviated, never cut: the
    kind's ``info`` (or its ``info_short`` when that does not fit), then the latency, the
    traffic and the failed sensors while they fit (the failed ones are kept, at the expense of
    the traffic)."""
    failed = f"failed {','.join(st['failed'])}" if st["failed"] else ""
    latency = f"{st['latency_ms']:.1f} ms"
    traffic = f"{st['messages']} msg {st['bytes'] / 1e3:.0f} kB"
    for info in (st["info"], st.get("info_short", st["info"])):
        for parts in ((info, latency, traffic, failed), (info, latency, failed), (info, failed)):
            text = "  ".join(p for p in parts if p)
            if len(text) <= width:
                return text
    return "  ".join(p for p in (st.get("info_short", st["info"]), failed) if p)


def up(
    kind: Any,
    sc: Any,
    config_path: str,
    out: Path,
    *,
    options: dict[str, Any] | None = None,
    realtime: bool = False,
    speed: float = 1.0,
    run_id: str,
    verbose: bool = False,
    on_ready: Callable[[Supervisor], None] | None = None,
    nodes: list[str] | None = None,
    router: str | None = None,
    netns: bool = False,
    topology: NetnsTopology | None = None,
    sensors_per_process: int | None = None,
    foxglove: str | None = None,
) -> int:
    """Run the network of ``sc`` (a config of the scenario kind ``kind``, with the run
    ``options`` already applied; they are passed on to every process) to completion; returns
    the manager's exit status (130 on Ctrl-C).

    ``nodes`` limits which processes this host starts (names: ``manager``, ``world``,
    ``recorder``, ``sensors`` for all sensors, or sensor ids); the others are started
    elsewhere (``python -m sensors ... --connect ROUTER``).  ``router`` overrides
    ``network.router``.

    ``netns``: each sensor in its own network namespace, linked to the manager's by an emulated
    link (:mod:`covnet.processes.netns_launch`, which calls back with ``topology``); not with
    ``nodes``
    or ``router``, and one sensor per process.

    ``sensors_per_process``: how many sensors one sensor process hosts (:mod:`sensors.host`;
    default :func:`default_sensors_per_process`); ``processes.json`` then also says which
    process hosts each sensor (``"hosts"``).

    ``foxglove``: ``HOST:PORT`` on which the recorder serves the visual channels live over the
    Foxglove WebSocket protocol (``covnet up --foxglove``; the recording has them anyway)."""
    options = options or {}
    if sensors_per_process is not None and sensors_per_process < 1:
        raise UpError(f"--sensors-per-process: must be >= 1, got {sensors_per_process}")
    if netns:
        if nodes is not None or router is not None:
            raise UpError("--netns runs the whole network here: not with --nodes or --router")
        if sensors_per_process not in (None, 1):
            raise UpError("--netns puts each sensor in its own namespace: one sensor per process")
        return up_in_namespaces(
            up, kind, sc, config_path, out, options=options, realtime=realtime, speed=speed,
            run_id=run_id, verbose=verbose, on_ready=on_ready, sensors_per_process=1,
            foxglove=foxglove,
        )  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    given_router = router  # --router (None: the config's)
    router = resolve_router(endpoint(sc.network, router or sc.network.router))
    wanted = set(nodes) if nodes is not None else None
    ids = list(sc.sensor_ids)  # the sensors started here, in config order
    if wanted is not None and "sensors" not in wanted:
        ids = [sid for sid in ids if sid in wanted]
    if sensors_per_process is None:
        sensors_per_process = default_sensors_per_process(len(ids))
    groups = sensor_hosts(ids, sensors_per_process)
    specs = process_specs(
        kind,
        sc,
        config_path,
        run_id,
        router,
        out,
        options=options,
        realtime=realtime,
        speed=speed,
        sensors_per_process=sensors_per_process,
        sensor_ids=ids,
        foxglove=foxglove,
    )
    if topology is not None:  # --netns: each process in its namespace, with its endpoint
        specs, router = topology.apply(specs), topology.listen
    else:  # forks of this launcher with the nodes' modules loaded (start-up time)
        preload = (*NODE_PRELOAD, *kind.roles.values())
        specs = [replace(sp, preload=preload) for sp in specs]
    if wanted is not None:
        sensor_procs = {name for name, _ in groups}
        specs = [sp for sp in specs if sp.name in wanted or sp.name in sensor_procs]
    hosts = hosted_by(groups)
    nodes_here = [sp.name for sp in specs if not sp.name.startswith(HOST_PREFIX)] + list(hosts)
    # keys, passwords: on this host; the certificates' names against the endpoint in use
    preflight(sc, nodes_here, str(config_path), router=given_router)
    if not any(sp.name == "manager" for sp in specs):
        # what the nodes connect to (process_specs): network.connect when the config gives
        # it, not the router endpoint resolved here (port 0 became a free port nobody uses)
        to = router if topology is not None else endpoint(sc.network, sc.network.connect or router)
        return _supervise_without_manager(specs, out, run_id, to, hosts)
    if topology is None and (taken := router_in_use(router)) is not None:
        raise UpError(f"--router: {taken}; nothing was started")
    ready = threading.Event()
    view = StatusView(sc.scans, kind.episodes(sc))
    restartable = {sp.name for sp in specs if sp.restart}

    def on_line(name: str, text: str) -> None:
        if name == "manager" and text.startswith("STATUS "):
            try:
                view.update(json.loads(text[7:]))
            except (ValueError, KeyError):
                view.line(f"[{name}] {text}")
            return
        if name == "manager" and text == "READY":
            ready.set()
        if shown(name, text, verbose):
            view.line(f"[{name}] {text}")

    view.line(f"[launcher] run {run_id}: router {router}, run directory {out}")
    if foxglove is not None and any(sp.name == "recorder" for sp in specs):
        view.line(f"[launcher] Foxglove live view: ws://{foxglove} (open it in Foxglove)")
    recorded_here = any(sp.name == "recorder" for sp in specs)
    facts = {  # what a rebuild from the recording cannot know (settle)
        "run_id": run_id,
        "clock": "realtime" if realtime else "lockstep",
        "speed": speed if realtime else None,
        "router": router,
    }
    # a SIGTERM or a hang-up stops the run as a Ctrl-C does; a handler can be installed from the
    # main thread only (``covnet.cli.main(["up", ...])`` called in a thread runs without them)
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, interrupts.raise_interrupt) if main else None
    previous_hup = signal.signal(signal.SIGHUP, interrupts.raise_interrupt) if main else None
    status = 0
    lost: dict[str, dict[str, Any]] = {}  # VITAL nodes that died and were not restarted
    sup = Supervisor(
        specs, on_line=on_line, pids_file=out / "processes.json", pids_extra=_hosts(hosts)
    )
    was_ready = False
    try:
        with (  # the children first: they may be forks of this process, while it has one thread
            sup,
            view,  # (on a terminal, rich's refresh thread)
        ):
            grace = READY_GRACE_S + READY_GRACE_PER_SENSOR_S * len(ids)
            deadline = time.monotonic() + sc.network.ready_timeout_s + grace
            while not ready.wait(0.1):
                rcs = sup.poll()
                if rcs.get("manager") is not None:
                    raise UpError(f"the manager exited with status {rcs['manager']} before READY")
                gone = gone_before_ready(rcs, restartable)
                if gone:  # a node that cannot start (a refused login, a bad file): fail now
                    name, rc = next(iter(gone.items()))
                    raise UpError(
                        f"{name} exited with status {rc} before the network was READY (its error "
                        "is above); nothing was run"
                    )
                if time.monotonic() > deadline:
                    raise UpError("the network did not become READY in time")
            was_ready = True
            if on_ready is not None:
                on_ready(sup)
            restarts_seen = 0
            while True:
                rcs = sup.poll()
                for name in (VITAL.keys() & rcs.keys()) - lost.keys():
                    code = rcs[name]
                    # died (a restartable one runs again); not one that left because the
                    # manager failed (EXIT_RUN_FAILED: the manager's exit says why)
                    if code not in (None, 0, EXIT_RUN_FAILED):
                        lost[name] = _lost(name, code, view.last)
                        view.line(f"[launcher] {lost[name]['ended']}")
                n = sum(sup.restarts.values())
                if n != restarts_seen:
                    restarts_seen = n
                    counts = {k: v for k, v in sup.restarts.items() if v}
                    view.line(f"[launcher] restarted: {counts}")
                if rcs["manager"] is not None:
                    status = int(rcs["manager"])
                    break
                time.sleep(0.05)
            final = sup.stop()
        others = {k: v for k, v in final.items() if k != "manager" and v not in (0, None)}
        if status != 0:
            why = f"the manager exited with status {status}{_its_error(sup, 'manager')}"
            ended = settle(kind, sc, out, facts, "failed", why, recorded_here=recorded_here)
            _note_restarts(out, sup.restarts)  # (into a run.json rebuilt from the recording too)
            ended += _note_lost(out, lost)
            raise UpError(f"the manager failed (exit status {status}); {ended}")
        _note_restarts(out, sup.restarts)
        # a world or recorder of another host down at the end, as the manager saw it (this
        # launcher watches only its own: the run was "completed", exit 0)
        here = {sp.name for sp in specs}
        for name, when in _gone_at_end(out).items():
            if name in VITAL and name not in here and name not in lost:
                lost[name] = _lost_elsewhere(name, when)
                view.line(f"[launcher] {lost[name]['ended']}")
        if lost:
            unsaid = _note_lost(out, lost)
            why = "; ".join(ev["ended"] for ev in lost.values())
            raise UpError(f"the run is not complete: {why}{unsaid or ' (run.json: status failed)'}")
        if others and not sc.network.restart == "on-failure":
            view.line(f"[launcher] note: processes that did not exit cleanly: {others}")
        return 0
    except UpError as exc:
        # before READY a node failed: the launcher stopped the manager, which then wrote
        # "interrupted" (as for a Ctrl-C); the run failed (the manager's own "failed" and its
        # reason are kept)
        if not was_ready and _run_info(out).get("status") != "failed":
            unsaid = _record_end(out, "failed", str(exc))
            if unsaid:
                raise UpError(f"{exc}{unsaid}") from None
        raise
    except KeyboardInterrupt:
        sup.stop()  # done already, unless the Ctrl-C came as the with statement took it
        ended = settle(
            kind, sc, out, facts, "interrupted", "interrupted (Ctrl-C, SIGTERM or a hang-up)",
            recorded_here=recorded_here,
        )  # fmt: skip
        _note_restarts(out, sup.restarts)  # the launcher printed them: run.json says them too
        ended += _note_lost(out, lost)
        with contextlib.suppress(OSError):  # a hang-up: the terminal may be gone
            print(f"covnet up: interrupted; every process stopped; {ended}", file=sys.stderr)
        return interrupts.EXIT_INTERRUPTED
    finally:
        if main:
            signal.signal(signal.SIGTERM, previous)
            signal.signal(signal.SIGHUP, previous_hup)


def _its_error(sup: Supervisor, name: str) -> str:
    """``" (<its last error line>)"`` of node ``name`` (``manager: error: ...``, which names a
    file that could not be written, a full ``$TMPDIR``'s spill file ...), for ``run.json``'s
    ``ended``; ``""`` when it said none."""
    said = [ln for ln in sup.output(name) if ln.startswith(f"{name}: error: ")]
    return f" ({said[-1]})" if said else ""


def settle(
    kind: Any,
    sc: Any,
    out: Path,
    run_info: dict[str, Any],
    status: str,
    why: str,
    *,
    recorded_here: bool = True,
) -> str:
    """After the network stopped: make sure ``out`` is a valid run directory and say what it
    holds.  The manager writes it when its loop ends (with ``run.json``'s ``status``); when it
    could not (killed, crashed, or stopped before READY), the directory is rebuilt from the
    recording by the kind's replay (``kind.rebuild``: every scan recorded complete) and marked
    ``status`` because of ``why``.  ``recorded_here``: the recorder ran under this launcher
    (else on another host: its recording is there, and nothing here says how many scans were
    done; this launcher said "nothing was recorded", ``scans_completed: 0``, after 25 scans)."""
    info = _run_info(out)
    if info.get("status") in STATUSES:
        return f"{out} holds the scans done ({info['status']}: {_scans(info)})"
    # the manager's live snapshot, left by a manager that died: the run is over
    with contextlib.suppress(OSError):
        (out / LIVE).unlink(missing_ok=True)
    recording = out / "recording.mcap"
    if not recorded_here and not recording.is_file():
        unsaid = _record_end(
            out, status, f"{why}; the recorder ran on another host: its recording holds the scans"
        )
        return (
            "the recorder ran on another host: the scans done are in its recording.mcap "
            f"there, not in {out}{unsaid}"
        )
    if not recording.is_file() or recording.stat().st_size == 0:
        if not out.is_dir() or not any(p.name != "processes.json" for p in out.iterdir()):
            # stopped before the manager wrote anything: no scan was done (run.json says so,
            # and covnet replay then that there is nothing to replay)
            unsaid = _record_end(out, status, f"{why}; nothing was recorded", scans_completed=0)
            return f"nothing was recorded ({out} holds no results){unsaid}"
        unsaid = _record_end(out, status, f"{why}; no recording to rebuild the results from")
        return f"no recording: {out} holds no results{unsaid}"
    try:
        report = kind.rebuild(
            sc,
            run_info["run_id"],
            kind.episodes(sc),
            recording,
            out,
            {**run_info, "mode": "network"},
        )
    except Exception as exc:  # noqa: BLE001 (whatever the recording holds, say it and go on)
        # a file that could not be written (a full disk) as FILE: why
        what = os_error_text(exc) if isinstance(exc, OSError) else str(exc)
        unsaid = _record_end(out, status, f"{why}; rebuilding from the recording failed: {what}")
        later = (
            f" (once it can be written, covnet replay {out} rebuilds them from the recording)"
            if isinstance(exc, OSError)
            else ""
        )
        return (
            f"the recording could not be rebuilt ({what}); {out} holds no complete "
            f"results{later}{unsaid}"
        )
    info = _run_info(out)
    scans = _scans(info)
    record_end(
        out,
        status,
        f"{why}; the results were rebuilt from the recording (covnet replay's code)",
        rebuilt_from_recording=True,
        rebuild_notes=list(getattr(report, "notes", [])),
        # what the manager would have written: its count of the failure and rejoin events,
        # which the rebuild recovered from the recorded Status messages
        membership=_rebuilt_membership(info, _summary(out)),
    )
    return f"rebuilt {out} from the recording up to the last complete scan ({scans})"


def _record_end(out: Path, status: str, why: str, **facts: Any) -> str:
    """:func:`~covnet.runs.rundir.try_record_end`: ``""``, or what to add to the message when
    ``run.json`` could not be written either (a full disk)."""
    unwritten = try_record_end(out, status, why, **facts)
    return f"; {out / RUN_INFO} does not say so ({unwritten})" if unwritten else ""


def _scans(info: dict[str, Any]) -> str:
    """``run.json``'s scans completed in words: ``"spectral 12, trace 0"`` or ``"12 scans"``."""
    done = info.get("scans_completed")
    if isinstance(done, dict):
        return ", ".join(f"{k} {v}" for k, v in done.items()) or "no scan"
    return f"{done} scans" if done is not None else "scans unknown"


def membership_of(failures: Any, scans_done: Any = None) -> dict[str, dict[str, int]]:
    """``run.json``'s ``membership`` from a run's failure events, counted as the manager counts
    them (:meth:`manager.loop.Bus.membership_changes`): per node that failed at least once, how
    often it ``failed`` and ``rejoined``.

    ``failures`` is one list of ``{"sensor", "scan", "event"}`` or such lists by episode, in
    the run's order, with ``scans_done`` (``{episode: scans}``) saying which episodes ran.
    Each episode's log starts from no failure (a node down as it starts is a ``failed`` event
    at its scan 1) while the manager counts each change of the failed set once over the run::

        F_e(k)  = F_e(k-1) xor {nodes of episode e's events at scan k},   F_e(0) = {}
        counts += F_e(k) xor F_prev   (each node: failed if in F_e(k), else rejoined)

    at every scan with events and at each episode's scan 1 (a node that came back between two
    episodes has no event there, but the manager counted its rejoin)."""
    if isinstance(failures, dict):
        done = scans_done if isinstance(scans_done, dict) else {}
        episodes = [evs for m, evs in failures.items() if done.get(m, 1)]
    else:
        episodes = [failures]
    counts: dict[str, dict[str, int]] = {}
    counted: frozenset[str] = frozenset()
    for evs in episodes:
        by_scan: dict[int, set[str]] = {1: set()}
        for ev in evs if isinstance(evs, list) else ():
            if isinstance(ev, dict) and ev.get("event") in ("failed", "rejoined"):
                by_scan.setdefault(int(ev.get("scan", 1)), set()).add(str(ev.get("sensor")))
        failed: frozenset[str] = frozenset()
        for k in sorted(by_scan):
            failed = failed ^ by_scan[k]
            for sid in sorted(failed ^ counted):
                c = counts.setdefault(sid, {"failed": 0, "rejoined": 0})
                c["failed" if sid in failed else "rejoined"] += 1
            counted = failed
    return dict(sorted(counts.items()))


def _rebuilt_membership(info: dict[str, Any], summary: dict[str, Any]) -> dict[str, Any]:
    if "peer" in summary:  # no fusion centre counts them: the monitor writes none (README)
        return {}
    if "failures" in info:  # the kinds whose run.json logs them (one list)
        return membership_of(info["failures"])
    return membership_of(summary.get("failures"), summary.get("scans_completed"))


def _summary(out: Path) -> dict[str, Any]:
    try:
        info = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def _hosts(hosts: dict[str, str]) -> dict[str, Any] | None:
    """``processes.json``'s ``"hosts"`` entry (sensor id -> its process), when a process hosts
    several sensors."""
    return {"hosts": hosts} if hosts else None


def _supervise_without_manager(
    specs: list[ProcessSpec], out: Path, run_id: str, router: str, hosts: dict[str, str]
) -> int:
    """Nodes only (the manager runs on another host): run until they all leave (they do when
    the manager's run ends) or Ctrl-C."""
    print(
        f"[launcher] run {run_id}: nodes {[s.name for s in specs]} -> router {router}", flush=True
    )
    sup = Supervisor(specs, pids_file=out / "processes.json", pids_extra=_hosts(hosts))
    try:
        with sup:
            while any(rc is None for rc in sup.poll().values()):
                time.sleep(0.1)
            final = sup.stop()
        bad = {k: v for k, v in final.items() if v != 0}
        for name, rc in sorted(bad.items()):
            if rc not in (EXIT_RUN_FAILED, EXIT_NO_RUN):  # those said why themselves
                what = f": {VITAL[name]}" if name in VITAL else ""
                print(f"[launcher] {name} failed (exit status {rc}){what}", flush=True)
        return 1 if bad else 0
    except KeyboardInterrupt:
        sup.stop()  # done already, unless the Ctrl-C came as the with statement took it
        print("covnet up: interrupted; every process stopped", file=sys.stderr)
        return interrupts.EXIT_INTERRUPTED


def shown(name: str, text: str, verbose: bool) -> bool:
    """Whether the launcher prints node ``name``'s output line ``text``: every line with
    ``--verbose``; else the manager's, a :data:`NOTE`, an error or a traceback."""
    return (
        verbose
        or name == "manager"
        or text.startswith(NOTE)
        or "error" in text.lower()
        or "Traceback" in text
    )


def _lost(name: str, rc: int, last: dict[str, Any] | None) -> dict[str, Any]:
    """``run.json``'s ``lost`` entry of a :data:`VITAL` node that died with status ``rc`` after
    the manager's STATUS ``last`` (None: before the first scan)."""
    scan = None if last is None else last.get("scan")
    episode = None if last is None else last.get("metric")
    return _lost_entry(
        name, rc, scan, episode, f"the {name} died (exit status {rc}) {{where}} and was not "
        "restarted",
    )  # fmt: skip


def _lost_entry(
    name: str, rc: int | None, scan: int | None, episode: str | None, what: str
) -> dict[str, Any]:
    """A ``lost`` entry: ``what`` with ``{where}`` (after which scan) filled in, then why it
    matters (:data:`VITAL`)."""
    where = "before the first scan" if not scan else f"after scan {scan}"
    if episode and scan:
        where += f" ({episode})"
    return {
        "node": name,
        "exit_status": rc,
        "after_scan": scan,
        "episode": episode,
        "ended": f"{what.format(where=where)}: {VITAL[name]}",
    }


def gone_before_ready(rcs: dict[str, int | None], restartable: set[str]) -> dict[str, int]:
    """The nodes that ended for good before READY (the launcher then fails at once, naming
    the first): a non-zero exit that will not be restarted, a restartable node's too when it
    found no run to join (``EXIT_NO_RUN``: not restarted; with ``restart: on-failure`` the
    launcher said only that the manager failed, hunt 13), never one that left with the run
    (``EXIT_RUN_FAILED``: the manager's exit says why)."""
    return {
        k: v
        for k, v in rcs.items()
        if v is not None
        and v not in (0, EXIT_RUN_FAILED)
        and (k not in restartable or v == EXIT_NO_RUN)
    }


def _gone_at_end(out: Path) -> dict[str, dict[str, Any]]:
    """``run.json``'s ``gone_at_end`` (the manager's: :meth:`manager.loop.Loop.note_vital`)."""
    gone = _run_info(out).get("gone_at_end")
    if not isinstance(gone, dict):
        return {}
    return {str(k): v for k, v in gone.items() if isinstance(v, dict)}


def _lost_elsewhere(name: str, when: dict[str, Any]) -> dict[str, Any]:
    """``run.json``'s ``lost`` entry of a :data:`VITAL` node of another host that the manager
    saw go after scan ``when["after_scan"]`` and not come back (its exit status is that
    host's)."""
    return _lost_entry(
        name, None, when.get("after_scan"), when.get("episode"),
        f"the {name}, on another host, was gone {{where}} to the end of the run",
    )  # fmt: skip


def _note_lost(out: Path, lost: dict[str, dict[str, Any]]) -> str:
    """A run whose world or recorder died (and was not restarted) is not complete, though the
    manager did every scan: ``run.json`` says ``failed`` and why, lists them under ``lost``,
    and both it and ``network.json`` count them as failed in ``membership``.  Best effort:
    ``""``, or what to add to the message when a file could not be written (a full disk: the
    recorder dies of it too)."""
    if not lost:
        return ""
    try:
        _write_lost(out, lost)
    except OSError as exc:
        return f"; {os_error_text(exc)}: the nodes lost are not recorded there"
    return ""


def _write_lost(out: Path, lost: dict[str, dict[str, Any]]) -> None:
    info = _run_info(out)
    membership = _with_lost(info.get("membership"), lost)
    net = out / "network.json"
    if net.is_file():
        try:
            stats = json.loads(net.read_text())
        except ValueError:
            stats = None
        if isinstance(stats, dict):
            stats["membership"] = _with_lost(stats.get("membership"), lost)
            write_json(net, stats)
    status = str(info.get("status")) if info.get("status") in STATUSES else "completed"
    why = "; ".join(ev["ended"] for ev in lost.values())
    if status == "completed":
        status, why = "failed", f"every scan done, but {why}"
    else:
        why = f"{info.get('ended', status)}; {why}"
    record_end(out, status, why, lost=list(lost.values()), membership=membership)


def _with_lost(membership: Any, lost: dict[str, dict[str, Any]]) -> dict[str, Any]:
    counts = dict(membership) if isinstance(membership, dict) else {}
    for name in lost:
        counts[name] = {**counts.get(name, {}), "failed": counts.get(name, {}).get("failed", 0) + 1}
    return counts


def _note_restarts(out: Path, restarts: dict[str, int]) -> None:
    path = out / "run.json"
    if not path.is_file():
        return
    summary = json.loads(path.read_text())
    summary["restarts"] = {k: v for k, v in restarts.items() if v}
    write_json(path, summary)
