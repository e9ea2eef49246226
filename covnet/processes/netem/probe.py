"""A small UDP echo probe for measuring an emulated link (run each end in its namespace).

::

    ip netns exec NS_B python -m covnet.processes.netem.probe echo --bind 10.77.0.2:9000
    ip netns exec NS_A python -m covnet.processes.netem.probe ping --to 10.77.0.2:9000 --count 100

``echo`` prints ``READY`` once bound and sends every datagram back until it has been idle for
``--idle`` seconds (or is stopped).  ``ping`` sends ``--count`` datagrams ``--interval`` seconds
apart without waiting for the echoes, keeps listening ``--wait`` seconds after the last one and
prints ``{"rtt_s": [...]}``: the round-trip time of each probe in send order, ``null`` for a
probe whose echo never came (time from just before ``sendto`` to the return of ``recv``, both
on the monotonic clock).
"""

from __future__ import annotations

import argparse
import json
import select
import socket
import struct
import sys
import time

_HEADER = struct.Struct("!Q")  #: probe number; the rest of a datagram is padding


def _host_port(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def echo(bind: tuple[str, int], idle: float) -> None:
    """Send every datagram back to its sender until ``idle`` seconds pass without one."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(bind)
        s.settimeout(idle)
        print("READY", flush=True)
        while True:
            try:
                data, peer = s.recvfrom(65536)
            except TimeoutError:
                return
            s.sendto(data, peer)


def ping(to: tuple[str, int], count: int, interval: float, wait: float, size: int) -> list:
    """Round-trip times (seconds, ``None`` for a lost probe) of ``count`` probes."""
    sent: list[float] = []
    rtt: list[float | None] = [None] * count
    pad = b"\0" * max(0, size - _HEADER.size)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.setblocking(False)
        start = time.monotonic()
        end = start + (count - 1) * interval + wait
        while True:
            now = time.monotonic()
            if len(sent) < count and now >= start + len(sent) * interval:
                sent.append(time.monotonic())
                s.sendto(_HEADER.pack(len(sent) - 1) + pad, to)
                continue
            if now >= end:
                return rtt
            next_send = start + len(sent) * interval if len(sent) < count else end
            ready, _, _ = select.select([s], [], [], max(0.0, min(next_send, end) - now))
            while ready:
                try:
                    data = s.recv(65536)
                except BlockingIOError:
                    break
                t = time.monotonic()
                (k,) = _HEADER.unpack_from(data)
                if k < len(sent) and rtt[k] is None:
                    rtt[k] = t - sent[k]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m covnet.processes.netem.probe", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("echo", help="echo datagrams back")
    e.add_argument("--bind", required=True, type=_host_port, help="HOST:PORT")
    e.add_argument("--idle", type=float, default=30.0, help="exit after this many idle seconds")
    q = sub.add_parser("ping", help="measure round-trip times")
    q.add_argument("--to", required=True, type=_host_port, help="HOST:PORT of an echo")
    q.add_argument("--count", type=int, default=100)
    q.add_argument("--interval", type=float, default=0.01, help="seconds between probes")
    q.add_argument("--wait", type=float, default=1.0, help="seconds to listen after the last")
    q.add_argument("--size", type=int, default=64, help="datagram bytes (>= 8)")
    args = p.parse_args(argv)
    if args.cmd == "echo":
        echo(args.bind, args.idle)
    else:
        rtt = ping(args.to, args.count, args.interval, args.wait, args.size)
        print(json.dumps({"rtt_s": rtt}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
