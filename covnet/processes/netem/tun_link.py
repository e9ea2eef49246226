"""A userspace link emulator: two TUN devices bridged by a forwarder that delays and drops packets.

The forwarder is one Python process per link (``python -m covnet.processes.netem.tun_link``, started
by
:func:`start_forwarder`).  It

1. creates TUN devices ``dev_a`` and ``dev_b`` (IFF_TUN | IFF_NO_PI: bare IP packets) in the root
   namespace, then moves them into ``ns_a`` and ``ns_b`` (``ip link set DEV netns NS``; the open
   fds stay with the forwarder), gives them ``addr_a`` and ``addr_b`` (one /30, so the connected
   route is there), turns IPv6 off on them (no stray router solicitations) and brings them up;
2. prints ``READY {json}`` and then forwards: every IP packet read from ``dev_a`` at monotonic
   time ``t`` (seconds since the start) gets its delivery time from a :class:`LinkState` of the
   ``a_to_b`` :class:`LinkSpec` (``None``: dropped), waits in a heap ordered by (delivery time,
   arrival order) and is written to ``dev_b`` when due; likewise ``b_to_a``.  One ``select``
   over both fds, sleeping until the next packet is due;
3. on SIGINT or SIGTERM (or when its parent dies: PR_SET_PDEATHSIG) closes both fds, which
   removes both devices, and prints ``STATS {json}``.

Draws come from :func:`covnet.core.delay.link_stream` ``(seed, link_index, 0)`` for ``a_to_b``
and ``(seed, link_index, 1)`` for ``b_to_a``: the n-th packet of a direction meets the same
loss/delay draws in every run with that seed (which packet is the n-th depends on the traffic).

Precision: a packet is never delivered before its due time counted from when the forwarder read
it; it is late by the wake-up latency of ``select`` plus Python's own work, typically 0.1-0.3 ms
on an idle machine and up to ~1 ms under load (the measured figures are in ``docs/netem.md``).
The read time is itself a little after the packet entered ``dev_a`` (same causes).
"""

from __future__ import annotations

import argparse
import ctypes
import heapq
import json
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from covnet.core.delay import LinkSpec, LinkState, link_stream
from covnet.processes.netem.detect import check_ip, open_tun

PR_SET_PDEATHSIG = 1
READ_BATCH = 64  #: packets read from one fd per wake-up before the due ones are written


class _Stop(Exception):
    """Raised by the signal handlers to leave the forwarding loop."""


@dataclass
class Direction:
    """One direction of the link: where packets come from and go to, and its counters."""

    name: str
    fd_in: int
    fd_out: int
    state: LinkState
    received: int = 0
    lost: int = 0
    forwarded: int = 0
    write_errors: int = 0

    def counters(self) -> dict[str, int]:
        return {
            "received": self.received,
            "lost": self.lost,
            "forwarded": self.forwarded,
            "write_errors": self.write_errors,
        }


def forward(directions: list[Direction], clock: Callable[[], float] = time.monotonic) -> None:
    """Forward packets until :class:`_Stop` (or another exception) is raised; see the module
    docstring.  ``clock`` gives seconds; times given to the :class:`LinkState` s start at 0."""
    t0 = clock()
    by_fd = {d.fd_in: d for d in directions}
    pending: list[tuple[float, int, int, bytes, Direction]] = []
    seq = 0
    while True:
        timeout = None if not pending else max(0.0, pending[0][0] - (clock() - t0))
        ready, _, _ = select.select(list(by_fd), [], [], timeout)
        for fd in ready:
            d = by_fd[fd]
            for _ in range(READ_BATCH):
                try:
                    packet = os.read(fd, 65536)
                except (BlockingIOError, InterruptedError):
                    break
                d.received += 1
                due = d.state.on_send(clock() - t0)
                if due is None:
                    d.lost += 1
                    continue
                heapq.heappush(pending, (due, seq, d.fd_out, packet, d))
                seq += 1
        now = clock() - t0
        while pending and pending[0][0] <= now:
            _, _, fd_out, packet, d = heapq.heappop(pending)
            try:
                os.write(fd_out, packet)
                d.forwarded += 1
            except OSError:
                d.write_errors += 1


def _place(dev: str, ns: str, addr: str) -> None:
    """Move ``dev`` into ``ns``, address it, IPv6 off, up."""
    check_ip("link", "set", dev, "netns", ns)
    check_ip("-n", ns, "addr", "add", addr, "dev", dev)
    # best effort: without IPv6 only the user's traffic crosses the link
    subprocess.run(
        ["ip", "netns", "exec", ns, "sysctl", "-q", "-w", f"net.ipv6.conf.{dev}.disable_ipv6=1"],
        capture_output=True,
        timeout=20,
    )
    check_ip("-n", ns, "link", "set", dev, "up")


def _die_with_parent() -> None:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def main(argv: list[str] | None = None) -> int:
    """The forwarder process (see the module docstring)."""
    p = argparse.ArgumentParser(
        prog="python -m covnet.processes.netem.tun_link", description=__doc__
    )
    for name in ("ns-a", "ns-b", "dev-a", "dev-b", "addr-a", "addr-b"):
        p.add_argument(f"--{name}", required=True)
    p.add_argument("--a-to-b", required=True, help="LinkSpec as JSON (LinkSpec.to_dict)")
    p.add_argument("--b-to-a", required=True, help="LinkSpec as JSON (LinkSpec.to_dict)")
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--link-index", type=int, default=0)
    p.add_argument("--parent", type=int, default=None, help="exit when this pid is not our parent")
    args = p.parse_args(argv)
    _die_with_parent()
    if args.parent is not None and os.getppid() != args.parent:
        return 1  # the parent died before PR_SET_PDEATHSIG took effect

    def stop(signum: int, frame: Any) -> None:
        raise _Stop

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    specs = {
        "a_to_b": LinkSpec.from_dict(json.loads(args.a_to_b)),
        "b_to_a": LinkSpec.from_dict(json.loads(args.b_to_a)),
    }
    fds: list[int] = []
    directions: list[Direction] = []
    try:
        fd_a = open_tun(args.dev_a)
        fds.append(fd_a)
        fd_b = open_tun(args.dev_b)
        fds.append(fd_b)
        _place(args.dev_a, args.ns_a, args.addr_a)
        _place(args.dev_b, args.ns_b, args.addr_b)
        for fd in fds:
            os.set_blocking(fd, False)
        directions = [
            Direction("a_to_b", fd_a, fd_b, LinkState(specs["a_to_b"], link_stream(
                args.seed, args.link_index, 0))),
            Direction("b_to_a", fd_b, fd_a, LinkState(specs["b_to_a"], link_stream(
                args.seed, args.link_index, 1))),
        ]  # fmt: skip
        print("READY " + json.dumps({"pid": os.getpid()}), flush=True)
        forward(directions)
    except _Stop:
        pass
    except Exception as exc:  # reported to the parent, which shows it
        print(f"ERROR {type(exc).__name__}: {exc}", flush=True)
        return 1
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        for fd in fds:
            os.close(fd)  # non-persistent TUN devices vanish with their last fd
        if directions:
            print("STATS " + json.dumps({d.name: d.counters() for d in directions}), flush=True)
    return 0


class Forwarder:
    """The parent's handle on a running forwarder process."""

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self.proc = proc
        self.output = ""
        self.stats: dict[str, dict[str, int]] | None = None
        #: its exit status when it had ended before :meth:`stop` (killed mid-run), else None
        self.died: int | None = None

    @property
    def pid(self) -> int:
        return self.proc.pid

    def _read_until_ready(self, timeout: float) -> None:
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        deadline = time.monotonic() + timeout
        buf = b""
        while b"READY" not in buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"the link forwarder was not ready in {timeout} s")
            ready, _, _ = select.select([fd], [], [], left)
            if ready:
                chunk = os.read(fd, 4096)
                if not chunk:
                    break
                buf += chunk
        self.output = buf.decode(errors="replace")
        if "READY" not in self.output:
            self.proc.wait(timeout=10)
            raise RuntimeError(
                f"the link forwarder exited ({self.proc.returncode}) before it was ready:\n"
                + self.output
            )

    def stop(self, grace: float = 3.0) -> None:
        """SIGINT, then SIGTERM, then SIGKILL, each given ``grace`` seconds; collects the
        forwarder's last output and its ``STATS``."""
        if self.proc.poll() is not None:
            self.died = self.proc.returncode
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if self.proc.poll() is not None:
                break
            try:
                self.proc.send_signal(sig)
                self.proc.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                continue
        rest, _ = self.proc.communicate(timeout=10)
        self.output += rest.decode(errors="replace")
        for line in self.output.splitlines():
            if line.startswith("STATS "):
                self.stats = json.loads(line[len("STATS ") :])


def start_forwarder(
    *,
    ns_a: str,
    ns_b: str,
    dev_a: str,
    dev_b: str,
    addr_a: str,
    addr_b: str,
    a_to_b: LinkSpec,
    b_to_a: LinkSpec,
    seed: int,
    link_index: int = 0,
    ready_timeout: float = 15.0,
) -> Forwarder:
    """Start the forwarder (a new session, so a terminal's Ctrl-C reaches only the caller, who
    stops it) and wait for READY; on any failure nothing is left running.  ``addr_a`` and
    ``addr_b`` carry their prefix (``10.77.0.1/30``)."""
    cmd = [
        sys.executable, "-m", "covnet.processes.netem.tun_link",
        "--ns-a", ns_a, "--ns-b", ns_b, "--dev-a", dev_a, "--dev-b", dev_b,
        "--addr-a", addr_a, "--addr-b", addr_b,
        "--a-to-b", json.dumps(a_to_b.to_dict()), "--b-to-a", json.dumps(b_to_a.to_dict()),
        "--seed", str(seed), "--link-index", str(link_index), "--parent", str(os.getpid()),
    ]  # fmt: skip
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
    )
    fw = Forwarder(proc)
    try:
        fw._read_until_ready(ready_timeout)
    except BaseException:
        fw.stop()
        raise
    return fw


if __name__ == "__main__":
    sys.exit(main())
