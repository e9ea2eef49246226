"""One emulated link between two network namespaces, by ``tc netem`` or by the userspace forwarder.

:func:`emulated_link` is the one entry point: it gives namespace ``ns_a`` the address ``addr_a``
and ``ns_b`` the address ``addr_b`` on a point-to-point link whose direction ``a -> b`` behaves as
``a_to_b`` and ``b -> a`` as ``b_to_a`` (:class:`covnet.core.delay.LinkSpec`), and removes it all
on exit.  Two ways to build it:

- ``"netem"``: a veth pair with a ``netem`` qdisc on each end's egress; exact kernel timing, but
  only where the kernel has ``sch_netem`` and only for the specs netem reproduces
  (:func:`netem_args`); not seeded;
- ``"userspace"``: two TUN devices and a forwarder process (:mod:`covnet.processes.netem.tun_link`);
any
  spec, seeded, ~0.1-1 ms late.

``mode="auto"`` takes netem when it is available and reproduces both directions, otherwise the
userspace forwarder.
"""

from __future__ import annotations

import functools
import ipaddress
import itertools
import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

from covnet.core.delay import LinkSpec
from covnet.processes.netem.detect import (
    can_make_namespaces,
    check_ip,
    netem_available,
    run_ip,
    tun_available,
)
from covnet.processes.netem.tun_link import start_forwarder

MODES = ("auto", "userspace", "netem")
_names = itertools.count()


class NamespaceError(RuntimeError):
    """Network namespaces cannot be made here; the message says why."""


@dataclass
class LinkInfo:
    """A live emulated link.  ``addr_a``/``addr_b`` are bare addresses (no prefix); ``pid`` is the
    forwarder's (``None`` for netem); ``stats`` holds the forwarder's per-direction counters
    (``received``, ``lost``, ``forwarded``, ``write_errors``) once the link is closed."""

    ns_a: str
    ns_b: str
    addr_a: str
    addr_b: str
    dev_a: str
    dev_b: str
    mode: str
    pid: int | None = None
    #: the forwarder's exit status when it died before the link was closed (None: it did not)
    died: int | None = None
    stats: dict[str, dict[str, int]] | None = field(default=None)


def _unique(prefix: str) -> str:
    """A name unique to this process and call, at most 15 characters (an interface name)."""
    name = f"{prefix}{os.getpid() % 100000}x{next(_names)}"
    if len(name) > 15:
        raise ValueError(f"interface name {name!r} is longer than 15 characters")
    return name


@contextmanager
def namespaces(count: int = 2, prefix: str = "cvn") -> Iterator[list[str]]:
    """``count`` fresh network namespaces (loopback up), deleted on exit whatever happens.

    Raises :class:`NamespaceError` when they cannot be made (not root, no ``ip``, no
    CAP_SYS_ADMIN)."""
    if not can_make_namespaces():
        raise NamespaceError("network namespaces need root and iproute2 ('ip')")
    made: list[str] = []
    try:
        for _ in range(count):
            ns = _unique(prefix)
            made.append(ns)  # before the add: a Ctrl-C while it ran left the namespace behind
            r = run_ip("netns", "add", ns)
            if r.returncode != 0:
                made.pop()  # (not made: another's of that name is not ours to delete)
                raise NamespaceError(f"cannot create a network namespace: {r.stderr.strip()}")
            run_ip("-n", ns, "link", "set", "lo", "up")
        yield made
    finally:
        for ns in made:
            run_ip("netns", "del", ns)


def _us(seconds: float) -> str:
    return f"{round(seconds * 1e6)}us"


def netem_args(spec: LinkSpec) -> list[str] | None:
    """The ``tc qdisc ... netem`` arguments that reproduce ``spec``, or ``None`` when netem
    cannot.  netem keeps packets in order only when every packet gets the same delay; with a
    random delay each packet keeps its own (overtakes happen), which is ``reorder = 1``.  So:

    - constant ``v``, no jitter: ``delay v`` (any ``reorder``: equal delays never overtake);
    - constant ``v`` with jitter ``j``: ``delay v j distribution normal``;
    - uniform ``[l, h]``, no jitter: ``delay (l+h)/2 (h-l)/2`` (netem's default jitter is uniform);
    - normal ``(μ, σ)`` with jitter ``j``: ``delay μ sqrt(σ² + j²) distribution normal``
      (netem's normal is a table, accurate to about 1/8 σ);

    a random delay needs ``reorder = 1``; exponential and empirical delays are userspace-only.
    ``loss p`` becomes ``loss random 100p%``."""
    d, j = spec.delay, spec.jitter_s
    if d.kind == "constant":
        args = ["delay", _us(d.value_s)] + ([_us(j), "distribution", "normal"] if j > 0 else [])
        random = j > 0
    elif d.kind == "uniform" and j == 0:
        half = 0.5 * (d.high_s - d.low_s)
        args, random = ["delay", _us(d.mean()), _us(half)], half > 0
    elif d.kind == "normal":
        std = math.hypot(d.std_s, j)
        args = ["delay", _us(d.mean_s)] + ([_us(std), "distribution", "normal"] if std else [])
        random = std > 0
    else:
        return None
    if random and spec.reorder < 1.0:
        return None
    if spec.loss > 0:
        args += ["loss", "random", f"{100 * spec.loss:.6g}%"]
    return [*args, "limit", "100000"]


@functools.cache
def _netem_here() -> bool:
    return netem_available()


def choose_mode(mode: str, a_to_b: LinkSpec, b_to_a: LinkSpec) -> str:
    """``"netem"`` or ``"userspace"`` for ``mode`` (see the module docstring); a ``ValueError``
    for an unknown mode or a spec netem cannot reproduce in ``"netem"`` mode, a ``RuntimeError``
    when the mode is not available here."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}; got {mode!r}")
    fits = netem_args(a_to_b) is not None and netem_args(b_to_a) is not None
    if mode == "netem":
        if not fits:
            raise ValueError(
                "tc netem cannot reproduce these LinkSpecs (exponential/empirical delay, or a "
                "random delay with reorder < 1); use mode='userspace'"
            )
        if not _netem_here():
            raise RuntimeError("this kernel has no netem qdisc (sch_netem)")
        return "netem"
    if mode == "auto" and fits and _netem_here():
        return "netem"
    if not tun_available():
        raise RuntimeError("no TUN devices here (/dev/net/tun missing or no CAP_NET_ADMIN)")
    return "userspace"


def _addresses(subnet: str) -> tuple[str, str, int]:
    net = ipaddress.ip_network(subnet)
    if net.version != 4 or net.num_addresses < 4:
        raise ValueError(f"subnet must be an IPv4 network of /30 or larger; got {subnet!r}")
    a, b = itertools.islice(net.hosts(), 2)
    return str(a), str(b), net.prefixlen


@contextmanager
def _netem_link(info: LinkInfo, prefix: int, a_to_b: LinkSpec, b_to_a: LinkSpec) -> Iterator[None]:
    """A veth pair ``dev_a``-``dev_b`` with netem on each end's egress."""
    check_ip("link", "add", info.dev_a, "type", "veth", "peer", "name", info.dev_b)
    try:
        for ns, dev, addr, spec in (
            (info.ns_a, info.dev_a, info.addr_a, a_to_b),
            (info.ns_b, info.dev_b, info.addr_b, b_to_a),
        ):
            check_ip("link", "set", dev, "netns", ns)
            check_ip("-n", ns, "addr", "add", f"{addr}/{prefix}", "dev", dev)
            if not spec.is_ideal:
                args = netem_args(spec)
                assert args is not None
                check_ip("netns", "exec", ns, "tc", "qdisc", "add", "dev", dev, "root", "netem",
                          *args)  # fmt: skip
            check_ip("-n", ns, "link", "set", dev, "up")
        yield
    finally:
        # deleting one end deletes the pair, wherever the ends are by now
        run_ip("-n", info.ns_a, "link", "del", info.dev_a)
        run_ip("link", "del", info.dev_a)


@contextmanager
def emulated_link(
    ns_a: str,
    ns_b: str,
    a_to_b: LinkSpec,
    b_to_a: LinkSpec | None = None,
    seed: int = 0,
    *,
    mode: str = "auto",
    link_index: int = 0,
    subnet: str = "10.77.0.0/30",
    ready_timeout: float = 15.0,
) -> Iterator[LinkInfo]:
    """A link between the existing namespaces ``ns_a`` and ``ns_b``: ``a -> b`` as ``a_to_b``,
    ``b -> a`` as ``b_to_a`` (default: an ideal direction).  ``ns_a`` gets the first host address
    of ``subnet``, ``ns_b`` the second (give each link of one namespace its own subnet).  The
    userspace forwarder draws from ``link_stream(seed, link_index, 0 | 1)``.  On exit the
    forwarder is stopped (SIGINT, SIGTERM, SIGKILL, 3 s each) and the devices are gone."""
    b_to_a = LinkSpec() if b_to_a is None else b_to_a
    chosen = choose_mode(mode, a_to_b, b_to_a)
    addr_a, addr_b, prefix = _addresses(subnet)
    tag = "cvv" if chosen == "netem" else "cvt"
    dev_a, dev_b = _unique(tag), _unique(tag)
    info = LinkInfo(ns_a, ns_b, addr_a, addr_b, dev_a, dev_b, chosen)
    if chosen == "netem":
        with _netem_link(info, prefix, a_to_b, b_to_a):
            yield info
        return
    fw = start_forwarder(
        ns_a=ns_a,
        ns_b=ns_b,
        dev_a=dev_a,
        dev_b=dev_b,
        addr_a=f"{addr_a}/{prefix}",
        addr_b=f"{addr_b}/{prefix}",
        a_to_b=a_to_b,
        b_to_a=b_to_a,
        seed=seed,
        link_index=link_index,
        ready_timeout=ready_timeout,
    )
    info.pid = fw.pid
    try:
        yield info
    finally:
        fw.stop()
        info.stats, info.died = fw.stats, fw.died
