"""What a manager process does around its loop, whatever the scenario kind: listen as the
network's router, print ``LISTENING``/``READY``/``STATUS``/``DONE`` lines for the launcher, write
the run directory as it goes, let the nodes leave before the router closes, set the exit code.
"""

from __future__ import annotations

import contextlib
import json
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from covnet.clock import Clock, WallClock
from covnet.config import NetworkSpec
from covnet.processes import output
from covnet.processes.node_kit import NOTE
from covnet.processes.process import EXIT_FAIL, EXIT_OK, open_bus
from covnet.runs.rundir import LIVE, record_end, utc_now, write_json
from covnet.wire import messages as msg
from covnet.wire import security
from covnet.wire.bus import Bus
from manager.loop import LoopResult, wait_for_nodes_to_leave

LINGER_S = 5.0
"""After the run, how long the manager waits for the sensors' last counts (they leave within
milliseconds of seeing its token go)."""


@dataclass
class Hooks:
    """The callbacks a manager loop takes (see :func:`manager.loop.run_scans`)."""

    on_ready: Callable[[], None]
    on_status: Callable[[dict[str, Any]], None]
    on_progress: Callable[[Any, bool], None]

    def kwargs(self) -> dict[str, Any]:
        """As keyword arguments of a manager loop's ``run``."""
        return {
            "on_ready": self.on_ready,
            "on_status": self.on_status,
            "on_progress": self.on_progress,
        }


def run_info(args: Any, endpoint: str) -> dict[str, Any]:
    """The process facts every manager writes to ``run.json``."""
    return {
        "run_id": args.run,
        "clock": "realtime" if args.realtime else "lockstep",
        "speed": args.speed,
        "router": endpoint,
    }


RunFn = Callable[..., LoopResult]
"""A manager loop: ``run(cfg, bus, run_id, clock, stop, *, realtime, on_ready, on_status,
on_progress)`` (:func:`manager.loop.run` with a kind's logic, or the peer observer)."""
WriteFn = Callable[[Path, Any, Any, dict[str, Any]], object]
"""A kind's run-directory writer: ``write(out, cfg, result, run_info)``."""


def main_around(
    args: Any,
    cfg: Any,
    stop: threading.Event,
    run: RunFn,
    write: WriteFn,
    *,
    run_info_extra: dict[str, Any] | None = None,
    write_every_s: float = 1.0,
) -> int:
    """``python -m manager``'s body for any kind: :func:`serve` the loop ``run`` of ``cfg``
    on the router endpoint of ``--listen`` (or the config), writing the run directory
    ``--out`` with ``write`` (``run.json`` gets :func:`run_info` and ``run_info_extra``)."""
    endpoint = router_endpoint(cfg.network, args.listen)
    out = Path(args.out)
    info = {**(run_info_extra or {}), **run_info(args, endpoint)}

    def run_loop(bus: Bus, clock: Clock, hooks: Hooks) -> LoopResult:
        return run(
            cfg, bus, args.run, clock, stop, realtime=args.realtime, linger_s=LINGER_S,
            **hooks.kwargs(),
        )  # fmt: skip

    return serve(
        args,
        cfg.network,
        cfg.sensor_ids,
        stop,
        endpoint,
        run_loop,
        lambda result: write(out, cfg, result, info),
        write_every_s=write_every_s,
    )


def router_endpoint(net: NetworkSpec, listen: str | None) -> str:
    endpoint = security.endpoint(net, listen or net.router)
    if endpoint.endswith(":0"):
        raise ValueError(f"--listen: give a concrete port, got {endpoint!r}")
    return endpoint


def serve(
    args: Any,
    net: NetworkSpec,
    sensor_ids: tuple[str, ...],
    stop: threading.Event,
    endpoint: str,
    run_loop: Callable[[Bus, Clock, Hooks], LoopResult],
    write: Callable[[Any], object],
    *,
    write_every_s: float = 1.0,
) -> int:
    """Open the router session, run ``run_loop(bus, clock, hooks)``, and write the run
    directory with ``write(result)`` once, when the loop has ended (completed, stopped by
    SIGINT/SIGTERM, or failed), then how it ended (:func:`covnet.runs.rundir.record_end`).  While
    it runs, the last STATUS goes to ``live.json`` (:data:`covnet.runs.rundir.LIVE`) at most every
    ``write_every_s``; that file is removed once the results are written (or could not be:
    an ``OSError``, a full disk, is raised naming the file, and :func:`covnet.processes.
    process.guarded` prints it in one line).  Exit 0, or 1 on an error."""
    out = Path(args.out)
    last_write = [0.0]
    last_status = [0.0]
    latest: list[dict[str, Any]] = []
    launcher_gone = threading.Event()
    ready = threading.Event()  # every node joined (READY)

    def tell(line: str) -> None:
        """A line for the launcher (its pipe).  Once the launcher has gone (killed, or its
        terminal closed: a hang-up), the write fails: stop the run and keep its results, as
        a Ctrl-C does (the manager died on the broken pipe, and every scan done was lost)."""
        if launcher_gone.is_set():
            return
        try:
            print(line, flush=True)
        except OSError:
            launcher_gone.set()
            output.silence()
            stop.set()

    def on_ready() -> None:
        ready.set()
        tell("READY")

    def on_status(st: dict[str, Any]) -> None:
        now = time.monotonic()
        latest[:] = [st]
        if now - last_status[0] >= 0.05 or st["scan"] == st["scans"]:
            tell("STATUS " + json.dumps(st))
            last_status[0] = now

    def on_progress(result: Any, episode_done: bool) -> None:
        now = time.monotonic()
        if latest and (episode_done or now - last_write[0] >= write_every_s):
            write_json(out / LIVE, {"status": "running", "updated_utc": utc_now(), **latest[0]})
            last_write[0] = now

    extra = security.zenoh_settings(
        net, "manager", "manager", listen=True, sensor_ids=sensor_ids, source=args.config
    )
    with open_bus(
        "router",
        listen=[endpoint],
        lease_ms=net.lease_ms,
        timeout_s=net.ready_timeout_s,
        stop=stop,
        extra_json5=extra,
    ) as bus:
        tell(f"LISTENING {endpoint}")
        result = run_loop(bus, WallClock(args.speed), Hooks(on_ready, on_status, on_progress))
        # the run is over (our token is gone): the nodes leave on their own; keep the router
        # up until they have, so that none is cut off mid-publish
        # (before READY, also the nodes not heard yet: they hear the end and leave at once)
        recorder = (msg.RECORDER_ID,) if net.record else ()
        late = () if ready.is_set() else (*sensor_ids, msg.WORLD_ID, *recorder)
        wait_for_nodes_to_leave(bus, args.run, timeout_s=5.0, stop=stop, expected=late)
    try:
        write(result)
        status, why = ending(result, stop, launcher_gone.is_set())
        # the world or recorder down at the end (NetStats.gone_at_end): the launcher of this
        # host says it when that node ran on another host (its own it watches itself)
        gone = getattr(result.stats, "gone_at_end", None)
        facts = {"gone_at_end": gone} if gone else {}
        record_end(out, status, why, membership=result.stats.membership_counts(), **facts)
    finally:  # the run is over: no live snapshot stays, also when the results could not be
        # written (a full disk: the OSError names the file; the launcher rebuilds or says so)
        with contextlib.suppress(OSError):
            (out / LIVE).unlink(missing_ok=True)
    if result.error and status == "failed":
        with contextlib.suppress(OSError):  # the launcher may have gone
            print(f"manager: error: {result.error}", file=sys.stderr, flush=True)
        return EXIT_FAIL
    for line in twice_sent(getattr(result.stats, "rejected_by_key", {})):
        tell(line)
    for line in config_refused(getattr(result.stats, "rejected_by_key", {})):
        tell(line)
    tell(f"DONE completed={result.completed} out={args.out}")
    return EXIT_OK


def twice_sent(rejected_by_key: Mapping[str, Mapping[str, int]]) -> list[str]:
    """A :data:`~covnet.processes.node_kit.NOTE` for each sensor whose measurements came twice
    (``duplicate`` in ``network.json``'s rejections: the same numbers again, not fused).  One
    sensor started on two hosts (or twice on one) runs the run twice over: only the counts
    said so (hunt 11); a replayed or forged copy is counted the same way."""
    lines = []
    for key, reasons in sorted(rejected_by_key.items()):
        n = reasons.get("duplicate", 0)
        if not n:
            continue
        try:
            sid = msg.parse_measurement_key(key)
        except ValueError:
            continue
        lines.append(
            f"{NOTE}{n} of {sid}'s measurements came twice (counted duplicate, not fused): is "
            f"{sid} run by two processes at once (started on two hosts)? Stop one"
        )
    return lines


def config_refused(rejected_by_key: Mapping[str, Mapping[str, int]]) -> list[str]:
    """A :data:`~covnet.processes.node_kit.NOTE` for each node refused mid-run because its
    heartbeats named another config (``config_mismatch`` on its heartbeat key): a node
    restarted (``restart: on-failure``) reads the config file again, and an edit made during
    the run (or a moved file) reaches it; it was kept out of the run, and only ``network.json``
    said so."""
    lines = []
    for key, reasons in sorted(rejected_by_key.items()):
        n = reasons.get("config_mismatch", 0)
        parts = key.split("/")
        if not n or len(parts) < 2 or parts[-3:-2] != ["hb"]:
            continue
        lines.append(
            f"{NOTE}{parts[-1]} ran another config than this run's from some point on ({n} "
            f"heartbeat(s) refused; was it restarted after the config file was edited?): it "
            "was kept out of the allocation and nothing it sent was fused"
        )
    return lines


def ending(
    result: Any, stop: threading.Event, launcher_gone: bool = False
) -> tuple[str, str]:
    """``(status, why)`` of a loop's ``result``: ``completed`` when every scan was done,
    ``interrupted`` when a signal stopped it (also before the network was ready: the loop's
    error then only says that it was stopped) or the launcher went (``launcher_gone``: the
    pipe of its lines broke), ``failed`` with its error, else ``failed``."""
    if result.completed and not result.error:
        return "completed", "every scan done"
    if stop.is_set():
        why = (
            "stopped: the launcher went away (killed, or its terminal closed)"
            if launcher_gone
            else "stopped by SIGINT or SIGTERM (Ctrl-C in the launcher)"
        )
        return "interrupted", f"{why}: {result.error}" if result.error else why
    if result.error:
        return "failed", str(result.error)
    return "failed", "the loop ended before its last scan"
