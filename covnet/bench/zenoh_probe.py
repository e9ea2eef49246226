"""The closed-loop zenoh probe of ``covnet bench up``: covnet's scan message pattern on bare
pub/sub, with nothing else (no allocation, filter, world, recorder, heartbeats or checks).

Per scan: the *commander* (a router session, like the manager) publishes one command of the size
of covnet's ``Command`` enabling every sensor; each of ``N`` *responders* answers with one message
of the size of covnet's ``Measurement`` on a key of its own; the next command goes out when all
``N`` answers are in.  Responders are hosted ``K`` per process as ``covnet up`` hosts sensors
(:mod:`sensors.host`, :class:`sensors.protocol.HostLoop`): one client session, one command
subscription and one thread per process, each responder its own liveliness token and publisher
(``--threads``: a thread and a subscription per responder on shares of the one session, how
covnet hosted sensors before; ``covnet bench up`` reports the ratio to both).
It reports scans per second (first command to last answer) and the
per-scan latency (command published -> last answer received), as covnet's manager reports its
loop (``network.json``: ``scans_per_s``, ``scan_latency``).  The sessions are covnet's own
(:class:`covnet.wire.zenoh_bus.ZenohBus`: the same zenoh config, FIFO subscriptions read by the
loop's thread), so the ratio of covnet's figures to the probe's is what covnet's protocol and
work cost on top of the transport.

``python -m covnet.bench.zenoh_probe commander --listen EP --run R --sensors N --scans S``: prints
``READY`` once every responder's liveliness token is up, ``RESULT {json}`` at the end.
``python -m covnet.bench.zenoh_probe responders --connect EP --run R --id 0 --id 1 ...``: serves
until
the commander says stop (or leaves).
``python -m covnet.bench.zenoh_probe tap --connect EP --run R``: a bare recording subscriber of
every message (the commander's ``--taps 1`` waits for it), ``TAP {count}`` at the stop: what a
recorder process costs the probe at the least (:func:`covnet.bench.up.probe`, ``taps``).
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

__all__ = ["command_bytes", "main", "measurement_bytes"]

#: how long the tap lets a burst gather before it drains it (the recorder's ``BATCH_S``, which
#: covnet may not import: a process package)
TAP_BURST_S = 0.005

#: the scan number heads every payload (``0``: stop)
_HEAD = struct.Struct("<q")


def command_bytes(n_sensors: int) -> int:
    """The size of covnet's encoded ``Command`` enabling ``n_sensors`` sensors (ids as
    :mod:`covnet.covariance_control.network_sizes` names them)."""
    from covnet.wire import messages as msg  # the probe's own process: start-up of the responders

    ids = tuple(f"S{1 + i % 8}.{1 + i // 8}" for i in range(n_sensors))
    return len(msg.encode(msg.Command(100, 100.0, ids, time.monotonic_ns(), episode=0)))


def measurement_bytes() -> int:
    """The size of covnet's encoded covariance-control ``Measurement``."""
    import numpy as np  # the probe's own process: start-up of the responders

    from covnet.wire import messages as msg

    m = msg.Measurement(
        sensor_id="S1.1",
        scan=100,
        t=100.0,
        z=np.zeros((1, 2)),
        R=np.eye(2),
        t_sent_ns=time.monotonic_ns(),
        episode=0,
        seq=100,
    )
    return len(msg.encode(m))


def _payload(scan: int, size: int) -> bytes:
    return _HEAD.pack(scan) + bytes(max(size - _HEAD.size, 0))


def _open(mode: str, endpoint: str, stop: threading.Event, timeout_s: float = 30.0) -> Any:
    from covnet.processes.process import open_bus  # zenoh: the probe's processes only (start-up)

    if mode == "router":
        return open_bus("router", listen=[endpoint], lease_ms=1000, timeout_s=timeout_s, stop=stop)
    return open_bus("client", connect=[endpoint], lease_ms=1000, timeout_s=timeout_s, stop=stop)


def commander(args: argparse.Namespace) -> int:
    stop = threading.Event()
    n, run = args.sensors, args.run
    with _open("router", args.listen, stop) as bus:
        alive = bus.watch_liveliness(f"probe/{run}/alive/*")
        replies = bus.subscribe(f"probe/{run}/meas/*")
        token = bus.declare_token(f"probe/{run}/alive/commander")
        up: set[str] = set()
        deadline = time.monotonic() + args.ready_timeout
        while len(up) < n + args.taps:
            ev = alive.recv(timeout=0.1)
            if ev is not None and not ev.key.endswith("/commander"):
                (up.add if ev.alive else up.discard)(ev.key)
            if time.monotonic() > deadline:
                print(f"probe: only {len(up)} of {n + args.taps} up", file=sys.stderr)
                return 1
        time.sleep(0.2)  # the responders' subscriptions reach the router
        print("READY", flush=True)
        key = f"probe/{run}/cmd"
        size = args.command_bytes
        lat: list[float] = []
        t_first = time.perf_counter()
        for k in range(1, args.scans + 1):
            t0 = time.perf_counter()
            bus.publish(key, _payload(k, size))
            got = 0
            while got < n:
                s = replies.recv(timeout=args.scan_timeout)
                if s is None:
                    print(f"probe: scan {k}: {got} of {n} answers", file=sys.stderr)
                    return 1
                if _HEAD.unpack_from(s.payload)[0] == k:
                    got += 1
            lat.append(time.perf_counter() - t0)
        wall = time.perf_counter() - t_first
        bus.publish(key, _payload(0, size))  # stop
        token.undeclare()
        lat.sort()
        result = {
            "scans": args.scans,
            "wall_s": wall,
            "scans_per_s": args.scans / wall,
            "p50_ms": 1e3 * lat[len(lat) // 2],
            "p99_ms": 1e3 * lat[min(len(lat) - 1, int(0.99 * len(lat)))],
        }
        print("RESULT " + json.dumps(result), flush=True)
        time.sleep(0.3)  # let the stop reach the responders before the router goes
    return 0


def responders(args: argparse.Namespace) -> int:
    """The responders ``args.id`` of one process: by default one loop for all (one session,
    one command subscription, one thread: :class:`sensors.protocol.HostLoop`'s layout);
    ``--threads``: a thread per responder, each with a subscription of its own on a share of
    the process's one session (covnet's layout before the host loop)."""
    stop = threading.Event()
    size = args.measurement_bytes
    errors: list[str] = []

    def serve(bus: Any, ids: list[str]) -> None:
        cmds = bus.subscribe(f"probe/{args.run}/cmd")
        keys = [f"probe/{args.run}/meas/{rid}" for rid in ids]
        tokens = [bus.declare_token(f"probe/{args.run}/alive/{rid}") for rid in ids]
        while not stop.is_set():
            s = cmds.recv(timeout=0.5)
            if s is None:
                continue
            k = _HEAD.unpack_from(s.payload)[0]
            if k == 0:
                break
            for key in keys:
                bus.publish(key, _payload(k, size))
        for token in tokens:
            token.undeclare()

    threaded = args.threads and len(args.id) > 1
    try:
        shared = _open("client", args.connect, stop) if threaded else None
    except Exception as exc:  # noqa: BLE001 (say it; the commander times out)
        print(f"probe: responders: {exc}", file=sys.stderr)
        return 1

    def one(ids: list[str]) -> None:
        try:
            bus = shared.share() if shared is not None else _open("client", args.connect, stop)
            with bus:
                serve(bus, ids)
        except Exception as exc:  # noqa: BLE001 (say it; the commander times out)
            errors.append(f"{ids}: {exc}")

    groups = [[rid] for rid in args.id] if threaded else [list(args.id)]
    threads = [threading.Thread(target=one, args=(g,), daemon=True) for g in groups]
    for th in threads:
        th.start()
    try:
        for th in threads:
            while th.is_alive():
                th.join(0.1)
    except KeyboardInterrupt:
        stop.set()
    finally:
        if shared is not None:
            shared.close()
    for e in errors:
        print(f"probe: responder {e}", file=sys.stderr)
    return 1 if errors else 0


def tap(args: argparse.Namespace) -> int:
    """A bare recording subscriber: every message of the run (``probe/RUN/**``), stamped on
    arrival and kept in memory, drained in bursts as covnet's recorder drains its own
    (:mod:`recorder.node`); nothing decoded, nothing written.  Its cost on the probe is the
    least any recorder process of every message can cost."""
    stop = threading.Event()
    kept: list[tuple[str, bytes, int]] = []
    with _open("client", args.connect, stop) as bus:
        sub = bus.subscribe_stamped(f"probe/{args.run}/**")
        token = bus.declare_token(f"probe/{args.run}/alive/tap-{args.id}")
        while True:
            s = sub.recv(timeout=0.5)
            if s is None:
                continue
            time.sleep(TAP_BURST_S)
            done = False
            while s is not None:
                kept.append((s.key, s.payload, s.t_recv_ns))
                if s.key.endswith("/cmd") and _HEAD.unpack_from(s.payload)[0] == 0:
                    done = True
                s = sub.try_recv()
            if done:
                break
        token.undeclare()
    print(f"TAP {len(kept)}", flush=True)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="covnet.bench.zenoh_probe", description=__doc__.splitlines()[0]
    )
    sub = p.add_subparsers(dest="role", required=True)
    c = sub.add_parser("commander")
    c.add_argument("--listen", required=True)
    c.add_argument("--run", required=True)
    c.add_argument("--sensors", type=int, required=True)
    c.add_argument("--scans", type=int, default=300)
    c.add_argument("--command-bytes", type=int, default=64)
    c.add_argument("--ready-timeout", type=float, default=60.0)
    c.add_argument("--scan-timeout", type=float, default=10.0)
    c.add_argument("--taps", type=int, default=0, help="recording taps to wait for")
    t = sub.add_parser("tap")
    t.add_argument("--connect", required=True)
    t.add_argument("--run", required=True)
    t.add_argument("--id", default="0")
    r = sub.add_parser("responders")
    r.add_argument("--connect", required=True)
    r.add_argument("--run", required=True)
    r.add_argument("--id", action="append", required=True)
    r.add_argument("--measurement-bytes", type=int, default=146)
    r.add_argument("--threads", action="store_true", help="a thread per responder")
    args = p.parse_args(argv)
    return {"commander": commander, "responders": responders, "tap": tap}[args.role](args)


if __name__ == "__main__":
    sys.exit(main())
