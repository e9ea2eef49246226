"""What a manager process does around its loop, whatever the scenario kind: listen as the
network's router, print ``LISTENING``/``READY``/``STATUS``/``DONE`` lines for the launcher, write
the run directory as it goes, let the nodes leave before the router closes, set the exit code.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from covnet import __version__, security
from covnet.bus import Bus
from covnet.clock import Clock, WallClock
from covnet.config import NetworkSpec
from covnet.process import EXIT_FAIL, EXIT_OK, open_bus
from covnet.rundir import utc_now
from manager.loop import LoopResult, wait_for_nodes_to_leave


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
        return run(cfg, bus, args.run, clock, stop, realtime=args.realtime, **hooks.kwargs())

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


def network_run_info(
    kind: str, result: Any, scans_done: int, run_info: dict[str, Any] | None, **facts: Any
) -> dict[str, Any]:
    """``run.json`` of a network run whose ``result`` logs its failures in one list: the kind,
    whether it completed, the scans done, the failure and rejoin events (their detection times
    apart, being wall-clock), the error if any, the kind's ``facts`` and the process's
    ``run_info``."""
    info: dict[str, Any] = {
        "created_utc": utc_now(),
        "covnet_version": __version__,
        "mode": "network",
        "kind": kind,
        **facts,
        "completed": result.completed,
        "scans_completed": scans_done,
        "failures": [{k: v for k, v in ev.items() if k != "detected_ns"} for ev in result.failures],
        "failure_detected_ns": [ev for ev in result.failures if "detected_ns" in ev],
        **(run_info or {}),
    }
    if result.error:
        info["error"] = result.error
    return info


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
    """Open the router session, run ``run_loop(bus, clock, hooks)``, write with ``write(result)``
    (after each episode, at most every ``write_every_s`` — less often when a write is slow, so
    that writing stays under a tenth of the time — and at the end); exit 0, or 1 on an error."""
    last_write = [time.monotonic()]
    last_status = [0.0]

    def on_ready() -> None:
        print("READY", flush=True)

    def on_status(st: dict[str, Any]) -> None:
        now = time.monotonic()
        if now - last_status[0] >= 0.05 or st["scan"] == st["scans"]:
            print("STATUS " + json.dumps(st), flush=True)
            last_status[0] = now

    gap_s = [write_every_s]  # at least write_every_s, and ten times the last write's cost

    def on_progress(result: Any, episode_done: bool) -> None:
        if episode_done or time.monotonic() - last_write[0] >= gap_s[0]:
            t0 = time.monotonic()
            write(result)
            last_write[0] = time.monotonic()
            gap_s[0] = max(write_every_s, 10.0 * (last_write[0] - t0))

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
        print(f"LISTENING {endpoint}", flush=True)
        result = run_loop(bus, WallClock(args.speed), Hooks(on_ready, on_status, on_progress))
        # the run is over (our token is gone): the nodes leave on their own; keep the router
        # up until they have, so that none is cut off mid-publish
        wait_for_nodes_to_leave(bus, args.run, timeout_s=5.0, stop=stop)
    write(result)
    if result.error:
        print(f"manager: error: {result.error}", file=sys.stderr, flush=True)
        return EXIT_FAIL
    print(f"DONE completed={result.completed} out={args.out}", flush=True)
    return EXIT_OK
