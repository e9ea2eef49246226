"""The observer of a peer-mode network (``fusion.mode: peer``): no fusion, no decisions.

In peer mode there is no fusion centre (:mod:`sensors.peer`); the manager process is only the
network's router and this monitor: it watches every node's ``peer/<id>/track`` and
``peer/<id>/status``, counts the traffic (local tracks included), prints the live status and
writes the run directory: per metric, every node's own estimates (``arrays.npz``), the
``peer`` block of ``summary.json`` (each node's RMSE and NEES, and whether all nodes enabled the
same sensors at every scan), and the failures the nodes reported.  Its liveliness token is the
run's: the nodes leave when it goes.  It reads the nodes' heartbeats for what they refused
(``network.json``'s ``rejected_by_node``, as the central manager's), and after the run lingers
for their last ones, which each node sends as it leaves.

Stopped (Ctrl-C to ``covnet up``), it still takes every Track and Status the nodes deliver
until they have left: the nodes advance without it, and the recorder records what they send
until the run is over, so an observer that stopped taking at once kept fewer scans than the
recording holds and ``covnet replay`` (which rebuilds every scan recorded) said DIFFERS.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from covnet.clock import Clock
from covnet.core.gaussian import is_spd
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.model import build_model
from covnet.covariance_control.peer_run import NodeLog, PeerResult
from covnet.processes.node_kit import config_id
from covnet.processes.runtime_stats import NetStats
from covnet.wire import messages as msg
from covnet.wire.bus import Bus
from manager.loop import ConfigRefusal, not_ready, take_heartbeat

STOPPED_LINGER_S = 1.0
"""Stopped: the longest time to keep taking the nodes' reports until they have left (stopped
with it, they leave within milliseconds; the launcher waits 5 s before its SIGTERM)."""


def run(
    sc: Scenario,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    *,
    realtime: bool = False,
    on_ready: Callable[[], None] | None = None,
    on_status: Callable[[dict[str, Any]], None] | None = None,
    on_progress: Callable[[PeerResult, bool], None] | None = None,
    linger_s: float = 0.0,
) -> PeerResult:
    """Watch the peer nodes until every live node has reported the last scan of the last
    episode (``completed``), or ``stop``, or no report for ``network.scan_timeout_s``; the
    episodes are the config's metrics (peer mode runs in lockstep only: ``realtime`` must be
    false).  ``linger_s``: afterwards, up to that long for the nodes' last heartbeats (their
    rejection counts), as :meth:`manager.loop.Loop.linger`, taking their last Tracks and
    Statuses too; after a ``stop`` (once the network was ready) up to
    ``min(linger_s, STOPPED_LINGER_S)``: the result holds every scan the nodes reported
    before they left, as the recording does."""
    if realtime:
        raise ValueError("--realtime: peer mode runs in lockstep only")
    metrics = list(sc.allocation.metrics)
    model = build_model(sc)
    ids = model.sensor_ids
    net = sc.network
    stats = NetStats()
    result = PeerResult(list(metrics), {e: {} for e in range(len(metrics))}, stats)
    subs = [
        bus.subscribe(msg.peer_keyexpr(run_id, "*")),
        bus.subscribe(msg.measurement_keyexpr(run_id)),  # the local tracks: counted only
        bus.subscribe(msg.heartbeat_keyexpr(run_id)),  # the nodes' rejection counts
    ]
    live = bus.watch_liveliness(msg.alive_keyexpr(run_id))
    token = bus.declare_token(msg.alive_key(run_id, "manager", "manager"))
    alive: set[str] = set()
    expected = {*ids, "world", *(("recorder",) if net.record else ())}
    hb_root = msg.heartbeat_keyexpr(run_id).removesuffix("*/*")
    reported: set[tuple[int, int]] = set()  # (episode, scan) whose status went to on_status
    # the world and recorder down, since after which scan (a world or recorder of another
    # host that died went unreported: Loop.note_vital's twin)
    vital = ("world", *(("recorder",) if net.record else ()))
    vital_down: dict[str, dict[str, Any]] = {}

    def note_vital(episode: str, last_scan: int) -> None:
        for node in vital:
            if node in alive:
                vital_down.pop(node, None)
            else:
                vital_down.setdefault(node, {"after_scan": last_scan, "episode": episode})
    t_loop = time.perf_counter_ns()
    t_prev = [time.perf_counter_ns()]  # when the previous scan was complete

    def drain_live() -> None:
        while (ev := live.try_recv()) is not None:
            node = ev.key.rsplit("/", 1)[-1]
            (alive.add if ev.alive else alive.discard)(node)

    own = config_id(sc)
    configs: dict[str, str | None] = {}  # the config each node's heartbeats name

    def take(s: Any) -> None:
        stats.received(s.key, len(s.payload))
        if s.key.startswith(hb_root):
            hb = take_heartbeat(stats, run_id, s, expected)
            if hb is not None:
                configs.setdefault(hb.node_id, hb.config)
            return
        if "/peer/" not in s.key:
            return
        try:
            node, what = msg.parse_peer_key(s.key)
            m: msg.Track | msg.Status = (
                msg.decode_as(s.payload, msg.Track)
                if what == "track"
                else msg.decode_as(s.payload, msg.Status)
            )
        except msg.WireError as exc:
            stats.reject(s.key, exc.reason)
            return
        except ValueError:
            stats.reject(s.key, "bad_key")
            return
        if m.node_id != node or node not in ids:
            stats.reject(s.key, "key_mismatch")
            return
        if not (0 <= m.episode < len(metrics) and 1 <= m.scan <= model.scans):
            stats.reject(s.key, "wrong_scan")
            return
        if isinstance(m, msg.Track) and not (m.x.shape == (4,) and is_spd(m.P)):
            stats.reject(s.key, "bad_measurement")
            return
        log = result.nodes[m.episode].get(node)
        if log is None:
            log = result.nodes[m.episode][node] = NodeLog()
        log.add(m)

    def drain() -> bool:
        """Take every message waiting; whether there was one."""
        got = False
        for sub in subs:
            while (s := sub.try_recv()) is not None:
                take(s)
                got = True
        return got

    def scan_done(e: int, k: int) -> bool:
        logs = result.nodes[e]
        return all(n in logs and logs[n].has_status(k) or n not in alive for n in ids)

    ready = False
    try:
        deadline = time.monotonic() + net.ready_timeout_s
        refusal = ConfigRefusal()  # another config's nodes: refused as the manager's loop does
        # every node alive and heard naming its config (one of another: the run is refused,
        # as the manager's loop refuses it; the nodes leave on the failed end)
        while not expected <= alive or not expected <= configs.keys():
            drain_live()
            while (s := subs[2].try_recv()) is not None:  # the heartbeats
                take(s)
            if (why := refusal.why(own, configs, expected <= configs.keys())) is not None:
                result.error = why
                return result
            if stop.is_set():
                result.error = "stopped before the network was ready"
                return result
            if time.monotonic() > deadline:
                result.error = not_ready(
                    net.ready_timeout_s, sorted(expected - alive), sorted(expected - configs.keys())
                )
                return result
            time.sleep(0.01)
        ready = True
        if on_ready is not None:
            on_ready()
        last_news = time.monotonic()
        e = 0
        k = 1
        while e < len(metrics):
            if stop.is_set():  # the reports already sent are taken below, as the nodes leave
                return result
            got = drain()
            drain_live()
            if got:
                last_news = time.monotonic()
            elif time.monotonic() - last_news > net.scan_timeout_s:
                result.error = (
                    f"no peer reported for {net.scan_timeout_s} s (episode {e}, scan {k})"
                )
                return result
            else:
                s = subs[0].recv(timeout=0.01)
                if s is not None:
                    take(s)
                    last_news = time.monotonic()
            while e < len(metrics) and scan_done(e, k):
                note_vital(metrics[e], k - 1)
                stats.scans_done += 1
                now_ns = time.perf_counter_ns()
                stats.loop_wall_ns = now_ns - t_loop
                stats.scan_latency_ns.append(now_ns - t_prev[0])  # previous scan -> this one
                t_prev[0] = now_ns
                _report(result, e, k, model.scans, metrics[e], ids, stats, on_status, reported)
                last = k == model.scans
                if on_progress is not None:
                    on_progress(result, last)
                e, k = (e + 1, 1) if last else (e, k + 1)
        drain_live()
        note_vital(metrics[-1], model.scans)
        stats.gone_at_end = {n: dict(v) for n, v in sorted(vital_down.items())}
        result.completed = True
    finally:
        # the run's end, on purpose (kept); with an error, the nodes leave saying so
        _done = bus.declare_token(
            msg.failed_key(run_id) if result.error else msg.done_key(run_id)
        )
        token.undeclare()
        # the nodes' last heartbeats, sent as they leave (what they refused to the end), and,
        # stopped, the Tracks and Statuses they sent meanwhile (the recording has them too)
        leaving = expected - {"world"}
        stopped = stop.is_set()
        deadline = time.monotonic() + (min(linger_s, STOPPED_LINGER_S) if stopped else linger_s)
        while time.monotonic() < deadline and (ready if stopped else not stop.is_set()):
            drain()
            drain_live()
            if not leaving & alive:
                drain()  # a report or heartbeat sent just before its token went
                break
            time.sleep(0.02)
        for sub in subs:
            sub.close()
        live.close()
    return result


def _report(
    result: PeerResult,
    e: int,
    k: int,
    scans: int,
    metric: str,
    ids: tuple[str, ...],
    stats: NetStats,
    on_status: Callable[[dict[str, Any]], None] | None,
    reported: set[tuple[int, int]],
) -> None:
    if on_status is None or (e, k) in reported:
        return
    reported.add((e, k))
    sts = [s for log in result.nodes[e].values() if (s := log.recent_status(k)) is not None]
    if not sts:
        return
    st = sts[0]
    n_msgs = sum(stats.recv_msgs.values())
    trace_P = float(np.mean([s.trace_P for s in sts]))
    agree = all(s.enabled == st.enabled for s in sts)
    on_status(
        {
            "metric": metric,
            "episode": e,
            "scan": k,
            "scans": scans,
            "enabled": list(st.enabled),
            "fused": sorted({n for s in sts for n in s.fused}, key=ids.index),
            "failed": list(st.failed),
            "trace_P": trace_P,
            "trace_Pd": st.trace_Pd,
            "latency_ms": stats.scan_latency_ns[-1] / 1e6 if stats.scan_latency_ns else 0.0,
            "messages": n_msgs,
            "bytes": sum(stats.recv_bytes.values()),
            "agree": agree,
            "info": (
                f"scan {k}/{scans}  enabled {','.join(st.enabled) or '-'}  "
                f"tr P {trace_P:.1f} / tr Pd {st.trace_Pd:.1f} (node mean)"
                + ("" if agree else "  NODES DISAGREE")
            ),
        }
    )
