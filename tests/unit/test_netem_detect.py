"""covnet.processes.netem without a network: capability probes, the LinkSpec -> netem mapping, mode
choice,
and the forwarder's scheduling loop on a pipe."""

from __future__ import annotations

import contextlib
import socket
import threading

import numpy as np
import pytest

from covnet.core.delay import DelayDist, LinkSpec, LinkState, link_stream, schedule
from covnet.processes.netem import detect, link, netem_args
from covnet.processes.netem.tun_link import Direction, _Stop, forward


def test_probes_answer_a_bool():
    assert isinstance(detect.tun_available(), bool)
    assert isinstance(detect.netem_available(), bool)


def test_probes_are_false_without_the_means(monkeypatch):
    monkeypatch.setattr(detect, "TUN_PATH", "/nonexistent/tun")
    assert detect.tun_available() is False
    monkeypatch.setattr(detect.os, "geteuid", lambda: 1000)
    assert detect.can_make_namespaces() is False
    assert detect.netem_available() is False


def _const(ms: float, **kw) -> LinkSpec:
    return LinkSpec(DelayDist("constant", value_s=ms * 1e-3), **kw)


@pytest.mark.parametrize(
    ("spec", "args"),
    [
        (_const(20), ["delay", "20000us"]),
        (_const(20, loss=0.25), ["delay", "20000us", "loss", "random", "25%"]),
        (
            _const(20, jitter_s=0.002, reorder=1.0),
            ["delay", "20000us", "2000us", "distribution", "normal"],
        ),  # fmt: skip
        (
            LinkSpec(DelayDist("uniform", low_s=0.005, high_s=0.025), reorder=1.0),
            ["delay", "15000us", "10000us"],
        ),
        (
            LinkSpec(DelayDist("normal", mean_s=0.01, std_s=0.003), jitter_s=0.004, reorder=1.0),
            ["delay", "10000us", "5000us", "distribution", "normal"],
        ),
        (LinkSpec(DelayDist("normal", mean_s=0.01)), ["delay", "10000us"]),
    ],
)
def test_netem_args_reproduce_the_spec(spec, args):
    assert netem_args(spec) == [*args, "limit", "100000"]


@pytest.mark.parametrize(
    "spec",
    [
        LinkSpec(DelayDist("exponential", mean_s=0.01), reorder=1.0),
        LinkSpec(DelayDist("empirical", samples_s=(0.01,))),
        LinkSpec(DelayDist("uniform", low_s=0.0, high_s=0.01)),  # random and FIFO
        _const(10, jitter_s=0.001, reorder=0.5),
        LinkSpec(DelayDist("uniform", low_s=0.0, high_s=0.01), jitter_s=0.001, reorder=1.0),
    ],
)
def test_netem_args_refuse_what_netem_cannot_do(spec):
    assert netem_args(spec) is None


def test_mode_choice(monkeypatch):
    with pytest.raises(ValueError, match="mode must be one of auto, userspace, netem"):
        link.choose_mode("tc", LinkSpec(), LinkSpec())
    exp = LinkSpec(DelayDist("exponential", mean_s=0.01))
    with pytest.raises(ValueError, match="mode='userspace'"):
        link.choose_mode("netem", exp, LinkSpec())
    monkeypatch.setattr(link, "tun_available", lambda: True)
    monkeypatch.setattr(link, "_netem_here", lambda: False)
    assert link.choose_mode("auto", _const(5), _const(5)) == "userspace"
    with pytest.raises(RuntimeError, match="no netem qdisc"):
        link.choose_mode("netem", _const(5), _const(5))
    monkeypatch.setattr(link, "_netem_here", lambda: True)
    assert link.choose_mode("auto", _const(5), _const(5)) == "netem"
    assert link.choose_mode("auto", exp, _const(5)) == "userspace"
    assert link.choose_mode("userspace", _const(5), _const(5)) == "userspace"
    monkeypatch.setattr(link, "tun_available", lambda: False)
    with pytest.raises(RuntimeError, match="no TUN devices"):
        link.choose_mode("userspace", _const(5), _const(5))


def test_subnet_addresses():
    assert link._addresses("10.77.0.0/30") == ("10.77.0.1", "10.77.0.2", 30)
    assert link._addresses("10.9.0.0/24") == ("10.9.0.1", "10.9.0.2", 24)
    with pytest.raises(ValueError, match="/30 or larger"):
        link._addresses("10.77.0.0/31")


class _StopOnFirstPacket(LinkState):
    def on_send(self, t_send: float) -> float | None:
        raise _Stop


def test_forward_loses_and_delivers_by_the_link_state():
    """The loop on datagram socket pairs (one packet a datagram, like a TUN fd): packets queued
    at once come out (after at most 20 ms) except those the batch schedule loses; a packet on
    the other direction 0.5 s later stops the loop."""
    spec = LinkSpec(DelayDist("uniform", low_s=0.001, high_s=0.02), loss=0.2, reorder=0.5)
    a, b, c = (socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM) for _ in range(3))
    for end in (a[0], b[0], c[0]):
        end.setblocking(False)
    n = 40
    d = Direction("a_to_b", a[0].fileno(), b[1].fileno(), LinkState(spec, link_stream(5, 0, 0)))
    stopper = Direction(
        "b_to_a", c[0].fileno(), b[1].fileno(), _StopOnFirstPacket(LinkSpec(), None)
    )
    for k in range(n):
        a[1].send(bytes([k]))
    timer = threading.Timer(0.5, lambda: c[1].send(b"!"))
    timer.start()
    try:
        with pytest.raises(_Stop):
            forward([d, stopper])
        got = []
        with contextlib.suppress(BlockingIOError):
            while True:
                got += list(b[0].recv(100))
    finally:
        timer.cancel()
        for end in (*a, *b, *c):
            end.close()
    lost = schedule(spec, np.zeros(n), link_stream(5, 0, 0)).lost
    assert d.received == n and d.lost == lost.sum() and d.forwarded == n - lost.sum()
    assert sorted(got) == [k for k in range(n) if not lost[k]]
