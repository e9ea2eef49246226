"""``covnet up --netns``: every sensor in its own network namespace, on a real emulated link.

Topology (names unique to the launcher's pid; ``j`` is the sensor's index in the config, from
1)::

    cvn<pid>m  (manager ns: manager/router, world, recorder; lo up)
       | 10.77.x.2 ------ emulated link j (covnet.processes.netem.emulated_link) ------ 10.77.x.1 |
    cvn<pid>s<j>  (sensor j's ns: its sensor process only)

- Each sensor link gets its own /30 out of ``10.77.0.0/16`` (link ``j`` is the ``j``-th /30):
  the sensor's end is its first host address, the manager's end the second.  The direction
  sensor -> manager behaves as ``network.latency`` ``uplink`` of that sensor, manager -> sensor
  as its ``downlink`` (:meth:`covnet.config.LatencySpec.link`), drawing from the same link
  streams as the application-level emulation (``link_stream(seed, j - 1, 0 | 1)``).
- The manager's router listens on ``0.0.0.0:PORT`` *inside the manager namespace*, which holds
  only its loopback and the manager's end of every link: that is its side of every link plus
  127.0.0.1, with one endpoint.  World and recorder connect over loopback
  (``tcp/127.0.0.1:PORT``), each sensor to its link's manager-side address.  ``PORT`` is the
  config's router port, or 7447 when the config says 0 (the namespace is fresh: nothing else
  listens there).
- Every node runs as ``ip netns exec NS python -m ...`` (``ip netns exec`` execs: the pid the
  supervisor holds and writes to ``processes.json`` is the Python process's) with
  ``--no-app-latency``: the packets are delayed, not the messages.
- Delays are scenario seconds, like the scan period: a ``--realtime --speed X`` run divides
  them (and the jitter) by ``X`` on the wire, so whether a measurement is on time does not
  depend on ``--speed``; loss is unchanged.  What does not scale is the transport's own timing
  (TCP's retransmission timeout is at least 200 ms of real time): at high speeds a lost
  segment costs relatively more.  In lockstep (no ``--realtime``) the delays are taken as they
  are.
- Namespaces, devices and forwarder processes are always removed on the way out: at the end,
  on an error, on Ctrl-C or SIGTERM, when a child crashed.  The forwarders are stopped with
  SIGINT, then SIGTERM, then SIGKILL (:meth:`covnet.processes.netem.tun_link.Forwarder.stop`) and
  die
  with the launcher if it is SIGKILLed (``PR_SET_PDEATHSIG``); only the namespace names
  (``ip netns list``) would then be left, to delete with ``ip netns del``.

After the run, ``run.json`` gets a ``netns`` entry: the namespaces, the router endpoint, each
link's addresses, mode (``userspace`` or ``netem``), forwarder pid, the link specs in scenario
and wall-clock seconds, and the forwarder's counters per direction (``received``, ``lost``,
``forwarded``, ``write_errors``; none for netem).
"""

from __future__ import annotations

import ipaddress
import json
import os
import shutil
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from covnet.core.delay import DelayDist, LinkSpec
from covnet.errors import UpError
from covnet.processes import interrupts
from covnet.processes.launch import ProcessSpec
from covnet.processes.netem import emulated_link, netem_available, tun_available
from covnet.processes.netem.detect import run_ip
from covnet.processes.netem.link import choose_mode
from covnet.runs.rundir import write_json
from covnet.wire.security import endpoint

__all__ = [
    "BASE_NET",
    "DEFAULT_PORT",
    "NetnsTopology",
    "SensorLink",
    "netns_topology",
    "scaled",
    "unsupported_reason",
    "up_in_namespaces",
]

BASE_NET = ipaddress.ip_network("10.77.0.0/16")  #: link j (from 0) gets the j-th /30 of it
DEFAULT_PORT = 7447  #: the router's port in the manager namespace when the config says 0
UP, DOWN = 0, 1  # link stream directions, as in covnet.wire.latency_bus
_MANAGER_SIDE = ("manager", "world", "recorder")
_APP_LEVEL_HINT = (
    "use the application-level emulation instead: covnet up CONFIG --realtime (delays applied "
    "inside the processes), or covnet run / covnet sweep (simulated time)"
)


def unsupported_reason() -> str | None:
    """Why ``--netns`` cannot run here (a readable sentence), or ``None`` when it can: it needs
    root, iproute2 (``ip``) and TUN devices (``/dev/net/tun``) or the kernel's ``netem``."""

    if os.geteuid() != 0:
        why = "network namespaces need root"
    elif shutil.which("ip") is None:
        why = "iproute2 ('ip') is not installed"
    elif not (tun_available() or netem_available()):
        why = "neither TUN devices (/dev/net/tun, CAP_NET_ADMIN) nor the kernel's netem qdisc"
    else:
        return None
    return f"--netns: {why}; {_APP_LEVEL_HINT}"


def scaled(spec: LinkSpec, speed: float) -> LinkSpec:
    """``spec`` with every delay parameter and the jitter divided by ``speed`` (loss and
    reorder unchanged): scenario seconds to wall-clock seconds in a ``--speed`` run."""
    if speed == 1.0:
        return spec
    d = spec.delay
    delay = DelayDist(
        d.kind,
        value_s=d.value_s / speed,
        low_s=d.low_s / speed,
        high_s=d.high_s / speed,
        mean_s=d.mean_s / speed,
        std_s=d.std_s / speed,
        offset_s=d.offset_s / speed,
        samples_s=tuple(s / speed for s in d.samples_s),
    )
    return replace(spec, delay=delay, jitter_s=spec.jitter_s / speed)


@dataclass
class SensorLink:
    """One sensor's namespace and link; ``uplink``/``downlink`` are in scenario seconds,
    ``wire_*`` what the link applies (wall-clock seconds)."""

    sensor_id: str
    index: int  # link index: the sensor's position in the config, from 0
    ns: str
    sensor_addr: str
    manager_addr: str
    uplink: LinkSpec
    downlink: LinkSpec
    wire_uplink: LinkSpec
    wire_downlink: LinkSpec
    info: Any = None  # covnet.processes.netem.LinkInfo once the link is up

    def describe(self) -> dict[str, Any]:
        info = self.info
        stats = getattr(info, "stats", None)
        return {
            "namespace": self.ns,
            "link_index": self.index,
            "sensor_addr": self.sensor_addr,
            "manager_addr": self.manager_addr,
            "devices": [info.dev_a, info.dev_b] if info is not None else None,
            "mode": getattr(info, "mode", None),
            "forwarder_pid": getattr(info, "pid", None),
            # its exit status when it died during the run (the sensor was cut off from then
            # on, and the counters died with it); None: it did not
            "forwarder_died": getattr(info, "died", None),
            "uplink": self.uplink.to_dict(),
            "downlink": self.downlink.to_dict(),
            "wire_uplink": self.wire_uplink.to_dict(),
            "wire_downlink": self.wire_downlink.to_dict(),
            # the forwarder's a_to_b is sensor -> manager
            "counters": None
            if stats is None
            else {"uplink": stats.get("a_to_b"), "downlink": stats.get("b_to_a")},
        }


@dataclass
class NetnsTopology:
    """What the launcher needs from the namespaces: where each process runs and which endpoint
    it listens on or connects to (:meth:`apply` rewrites the process specs)."""

    manager_ns: str
    port: int
    listen: str  # the manager's router endpoint (in its namespace)
    loopback: str  # world and recorder connect here
    links: dict[str, SensorLink] = field(default_factory=dict)
    speed: float = 1.0  # scenario seconds per wall-clock second on the wire

    @property
    def namespaces(self) -> list[str]:
        return [self.manager_ns, *(lk.ns for lk in self.links.values())]

    def namespace_of(self, name: str) -> str:
        if name in _MANAGER_SIDE:
            return self.manager_ns
        return self.links[name].ns

    def endpoint_of(self, name: str, proto: str = "tcp") -> str:
        """The endpoint ``name`` listens on (manager) or connects to (everyone else)."""
        if name == "manager":
            return self.listen
        if name in _MANAGER_SIDE:
            return self.loopback
        return f"{proto}/{self.links[name].manager_addr}:{self.port}"

    def apply(self, specs: list[ProcessSpec]) -> list[ProcessSpec]:
        """Each spec run in its namespace (``ip netns exec NS``), with its endpoint and
        ``--no-app-latency``."""
        proto = self.listen.partition("/")[0]
        out = []
        for sp in specs:
            argv = list(sp.argv)
            for opt in ("--listen", "--connect"):
                if opt in argv:
                    argv[argv.index(opt) + 1] = self.endpoint_of(sp.name, proto)
            argv = ["ip", "netns", "exec", self.namespace_of(sp.name), *argv, "--no-app-latency"]
            out.append(replace(sp, argv=argv))
        return out

    def describe(self) -> dict[str, Any]:
        """The ``netns`` entry of ``run.json``."""
        return {
            "manager_namespace": self.manager_ns,
            "namespaces": self.namespaces,
            "router_listen": self.listen,
            "loopback_endpoint": self.loopback,
            "speed": self.speed,
            "links": {sid: lk.describe() for sid, lk in self.links.items()},
        }


def _port(router: str) -> int:
    port = int(router.rpartition(":")[2])
    return port if port != 0 else DEFAULT_PORT


def link_subnet(index: int) -> ipaddress.IPv4Network:
    """The /30 of link ``index`` (from 0) in :data:`BASE_NET`."""
    if not 0 <= index < BASE_NET.num_addresses // 4:
        raise ValueError(f"link index {index} out of range for {BASE_NET}")
    base = int(BASE_NET.network_address) + 4 * index
    return ipaddress.IPv4Network((base, 30))


@contextmanager
def _namespace(name: str) -> Iterator[str]:
    # the add inside the try: a Ctrl-C while `ip netns add` ran (the namespace made, its
    # return not seen) left it behind; the name is this process's (its pid), so deleting it
    # whatever happened deletes nothing of another's
    try:
        r = run_ip("netns", "add", name)
        if r.returncode != 0:
            raise RuntimeError(f"cannot create network namespace {name}: {r.stderr.strip()}")
        r = run_ip("-n", name, "link", "set", "lo", "up")
        if r.returncode != 0:
            raise RuntimeError(f"cannot bring up lo in {name}: {r.stderr.strip()}")
        yield name
    finally:
        run_ip("netns", "del", name)


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM ignored meanwhile (the teardown must run to its end); a no-op
    outside the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


class _LinkHolder(threading.Thread):
    """Opens one link (``cm``, an :func:`~covnet.processes.netem.emulated_link`) and holds it until
    released, in its own thread: the links start in parallel (a forwarder takes most of a
    second to start), and each forwarder's parent thread lives as long as the link (the
    forwarder's ``PR_SET_PDEATHSIG`` fires when the *thread* that started it ends)."""

    def __init__(self, link: SensorLink, cm: Any) -> None:
        super().__init__(name=f"netns-link-{link.sensor_id}", daemon=True)
        self.link, self.cm = link, cm
        self.ready = threading.Event()  # up, or failed (``error``)
        self.release = threading.Event()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            with self.cm as info:
                self.link.info = info
                self.ready.set()
                self.release.wait()
        except BaseException as exc:  # handed to the main thread
            self.error = exc
        finally:
            self.ready.set()


def _release(holders: list[_LinkHolder]) -> None:
    """Close every link (forwarders stopped: SIGINT, SIGTERM, SIGKILL) and wait for it."""
    for h in holders:
        h.release.set()
    for h in holders:
        if h.is_alive() or h.ident is not None:
            h.join(timeout=60.0)


@contextmanager
def netns_topology(
    sc: Any,
    *,
    speed: float = 1.0,
    mode: str = "auto",
    tag: str | None = None,
) -> Iterator[NetnsTopology]:
    """Build the namespaces and links of ``sc`` (any scenario kind with ``sensor_ids`` and
    ``network``; see the module docstring) and remove them all on exit, whatever happens.
    ``speed`` divides the link delays (a real-time run's ``--speed``; 1 in lockstep); ``mode`` goes
    to :func:`covnet.processes.netem.emulated_link`; ``tag`` (default: this pid) makes the names
    unique.
    Raises ``RuntimeError`` when a namespace or link cannot be made (nothing is left then)."""

    tag = str(os.getpid()) if tag is None else tag
    net = sc.network
    port = _port(net.router)
    topo = NetnsTopology(
        manager_ns=f"cvn{tag}m",
        port=port,
        listen=endpoint(net, f"tcp/0.0.0.0:{port}"),
        loopback=endpoint(net, f"tcp/127.0.0.1:{port}"),
        speed=speed,
    )
    lat = net.latency
    seed = int(getattr(sc, "seed", 0))
    stack = ExitStack()
    try:
        stack.enter_context(_namespace(topo.manager_ns))
        for j, sid in enumerate(sc.sensor_ids):
            subnet = link_subnet(j)
            hosts = list(subnet.hosts())
            up, down = lat.link(sid, "uplink"), lat.link(sid, "downlink")
            lk = SensorLink(
                sensor_id=sid,
                index=j,
                ns=f"cvn{tag}s{j + 1}",
                sensor_addr=str(hosts[0]),
                manager_addr=str(hosts[1]),
                uplink=up,
                downlink=down,
                wire_uplink=scaled(up, speed),
                wire_downlink=scaled(down, speed),
            )
            topo.links[sid] = lk
            stack.enter_context(_namespace(lk.ns))
        # each link's mode chosen here, once: the probes behind it are not for threads
        modes = {
            sid: choose_mode(mode, lk.wire_uplink, lk.wire_downlink)
            for sid, lk in topo.links.items()
        }
        holders = [
            _LinkHolder(
                lk,
                emulated_link(
                    lk.ns,
                    topo.manager_ns,
                    lk.wire_uplink,  # a -> b: sensor -> manager
                    lk.wire_downlink,
                    seed,
                    mode=modes[lk.sensor_id],
                    link_index=lk.index,
                    subnet=str(link_subnet(lk.index)),
                ),
            )
            for lk in topo.links.values()
        ]
        stack.callback(_release, holders)  # closed before the namespaces go
        for h in holders:
            h.start()
        for h in holders:
            while not h.ready.wait(0.1):  # sliced: Ctrl-C is handled meanwhile
                pass
        errors = [h.error for h in holders if h.error is not None]
        if errors:
            raise errors[0]
        yield topo
    finally:
        with _signals_deferred():
            stack.close()  # links (forwarders stopped, devices gone), then namespaces


def dead_links(topo: NetnsTopology) -> list[str]:
    """What to say of each link whose forwarder died during the run (a sensor cut off by its
    link looked like a failed sensor, and its counters were null without a reason)."""
    return [
        f"the link of {sid} died during the run (its forwarder's exit status {died}): "
        f"{sid} was cut off from then on, and the link's counters are lost"
        for sid, lk in topo.links.items()
        if (died := getattr(lk.info, "died", None)) is not None
    ]


def note_topology(out: Path, topo: NetnsTopology) -> None:
    """Merge ``topo.describe()`` into ``out/run.json`` under ``netns`` (``out/netns.json``
    when the manager wrote no ``run.json``)."""

    path = out / "run.json"
    if path.is_file():
        data = json.loads(path.read_text())
        data["netns"] = topo.describe()
        write_json(path, data)
    else:
        write_json(out / "netns.json", {"netns": topo.describe()})


def up_in_namespaces(
    up: Callable[..., int],
    kind: Any,
    sc: Any,
    config_path: str,
    out: Path,
    *,
    realtime: bool,
    speed: float,
    **kwargs: Any,
) -> int:
    """``covnet up --netns``: build the topology, run :func:`covnet.processes.up.up` in it (``up``
    is
    that function, passed in to keep the imports one way), remove the topology, note it in
    ``run.json``.  Returns ``up``'s status (130 on Ctrl-C or SIGTERM, also during set-up);
    a topology that cannot be built is an :class:`covnet.errors.UpError`."""
    reason = unsupported_reason()
    if reason is not None:
        raise UpError(reason)
    out.mkdir(parents=True, exist_ok=True)
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, interrupts.raise_interrupt) if main else None
    topo: NetnsTopology | None = None
    built = False
    try:
        try:
            with netns_topology(sc, speed=speed if realtime else 1.0) as topo:
                built = True
                n = len(topo.links)
                modes = sorted({str(lk.info.mode) for lk in topo.links.values()})
                print(
                    f"[launcher] netns: manager in {topo.manager_ns}, {n} sensors in their own "
                    f"namespaces, links {'/'.join(modes) or '-'}",
                    flush=True,
                )
                return up(
                    kind,
                    sc,
                    config_path,
                    out,
                    realtime=realtime,
                    speed=speed,
                    topology=topo,
                    **kwargs,
                )
        except (RuntimeError, TimeoutError, OSError) as exc:
            if built or isinstance(exc, UpError):
                raise
            raise UpError(f"--netns: cannot build the emulated network: {exc}") from None
    except KeyboardInterrupt:
        print("covnet up: interrupted; every process, link and namespace removed", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if topo is not None:
            note_topology(out, topo)
            for line in dead_links(topo):
                print(f"[launcher] {line}", file=sys.stderr, flush=True)
