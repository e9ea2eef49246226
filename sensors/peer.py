"""A peer node (``fusion.mode: peer``): a sensor that also fuses, with no fusion centre.

Every node runs, per metric episode and scan ``k`` (lockstep)::

    1. members(k): itself and every node whose Status(k-1) it received; it waits for each
       node's Status(k-1) until it arrives or the node's liveliness token goes (scan 1: every
       node whose token is up at the start).  Statuses go to every node through the router, so
       every node sees the same set: a node that died before publishing its status is out
       for everyone, one that published it is in for everyone.
    2. the decision: the same deterministic function of shared information on every node,
       the kind's engine (:class:`covnet.covariance_control.engine.ScanEngine` with this node
       only): :func:`covnet.covariance_control.decentral.decide_rule` over the *covariance
       mirror* (every node's fused covariance and every local filter's covariance follow from
       the config and the agreed enabled sets alone), the failed nodes infeasible, a subset
       scored by its worst live node.
    3. if enabled: measure (truth from the world), update the local filter, publish its
       LocalTrack on its own measurement key.
    4. collect the LocalTracks of its enabled neighbours (the communication graph of
       ``fusion.peer``: a node subscribes to its neighbours' keys only) until all arrived,
       a neighbour died or ``network.scan_timeout_s`` passed.
    5. fuse its own prediction with its own and its neighbours' tracks (``fusion.peer.rule``),
       publish its Track and Status (``node_id`` set) on its ``peer/<id>/`` keys.

The mirror advances with the *decided* subset (what every node knows), so decisions stay
identical on every node even when a track is lost.  A node that died stays out for the rest of
the run (peer mode does not restart nodes).  A node stopped (Ctrl-C) during a scan publishes
nothing of that scan: its waits were cut short, so whom it would name failed and what it would
fuse are not the network's (it named every peer whose status had not come yet failed).
Malformed messages are counted and dropped, and so are well-formed ones a node cannot use: a
track or status of a scan beyond the next one (``wrong_scan``: no peer can be further ahead in
lockstep) or outside the run (``bad_scan``), a truth outside the run, and a neighbour's track
that fails the node's validation gate
(``outside_gate``, :meth:`covnet.covariance_control.engine.ScanEngine.verdict`): among a
neighbour's tracks of a scan the node fuses the first that passes it, the others are counted.
A track the node never took is counted when it is dropped: it came after the node had fused
its scan (``late``) or is of a neighbour the scan did not enable (``not_enabled``).
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable, Collection, Container, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

from covnet.clock import Clock
from covnet.covariance_control.centre import usable_track
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.decentral import neighbours
from covnet.covariance_control.engine import ScanEngine, SensorSide, Tracked
from covnet.covariance_control.model import build_model
from covnet.processes.node_kit import (
    WORLD_GONE_WAIT_S,
    Heartbeat,
    ManagerWatch,
    config_id,
    manager_appear_s,
    manager_grace_s,
    world_returns,
)
from covnet.wire import messages as msg
from covnet.wire.bus import Bus, Sample
from sensors.protocol import TRUTHS_NEAR


@dataclass
class PeerStats:
    scans: int = 0
    tracks_sent: int = 0
    tracks_fused: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    #: the node left because the run did not end well: the monitor ended it with an error or
    #: went away without ending it (:attr:`~covnet.processes.node_kit.ManagerWatch.crashed`)
    manager_lost: bool = False


MAX_CANDIDATES = 4
"""Tracks a node keeps of one neighbour's scan (the genuine one and copies or forgeries); more
are counted ``duplicate``."""


class _Inbox:
    """What a node has heard: statuses (node, episode, scan), neighbours' tracks (up to
    :data:`MAX_CANDIDATES` per node and scan), truth, peers' liveliness; ``at``: the node's
    own ``(episode, scan)``, which bounds what it keeps (module docstring)."""

    def __init__(
        self,
        bus: Bus,
        run_id: str,
        me: str,
        nbr_ids: Sequence[str],
        stats: PeerStats,
        episodes: int,
        scans: int,
    ):
        self.stats = stats
        self.me = me
        self.episodes, self.scans = episodes, scans
        self.at = (0, 1)
        self.status_sub = bus.subscribe(msg.peer_keyexpr(run_id, "status"))
        self.track_subs = [bus.subscribe(msg.measurement_key(run_id, n)) for n in nbr_ids]
        self.truth_sub = bus.subscribe(msg.truth_key(run_id))
        self.live_sub = bus.watch_liveliness(msg.alive_keyexpr(run_id))  # every role
        self.statuses: set[tuple[str, int, int]] = set()
        self.tracks: dict[tuple[str, int, int], list[msg.LocalTrack]] = {}
        self.wanted: dict[tuple[int, int], frozenset[str]] = {}  # a fused scan's neighbours
        self.truth: dict[int, np.ndarray] = {}
        self.alive: set[str] = set()

    def drain(self) -> None:
        while (ev := self.live_sub.try_recv()) is not None:
            try:
                _, node = msg.parse_alive_key(ev.key)
            except ValueError:
                self.stats.rejected["bad_key"] += 1
                continue
            (self.alive.add if ev.alive else self.alive.discard)(node)
        while (s := self.status_sub.try_recv()) is not None:
            self._status(s)
        for sub in self.track_subs:
            while (s := sub.try_recv()) is not None:
                try:
                    tr = msg.decode_as(s.payload, msg.LocalTrack)
                    sender = msg.parse_measurement_key(s.key)
                except msg.WireError as exc:
                    self.stats.rejected[exc.reason] += 1
                    continue
                except ValueError:
                    self.stats.rejected["bad_key"] += 1
                    continue
                if sender != tr.sensor_id:
                    self.stats.rejected["key_mismatch"] += 1
                elif not usable_track(tr):
                    self.stats.rejected["bad_measurement"] += 1
                elif (why := self._outside(tr.episode, tr.scan)) is not None:
                    self.stats.rejected[why] += 1
                elif len(c := self.tracks.setdefault((sender, tr.episode, tr.scan), [])) < (
                    MAX_CANDIDATES
                ):
                    c.append(tr)
                else:
                    self.stats.rejected["duplicate"] += 1
        while (s := self.truth_sub.try_recv()) is not None:
            try:
                t = msg.decode_as(s.payload, msg.Truth)
            except msg.WireError as exc:
                self.stats.rejected[exc.reason] += 1
                continue
            if not 1 <= t.scan <= self.scans:
                self.stats.rejected["bad_scan"] += 1
            elif t.states.ndim == 2 and t.states.shape[0] >= 1 and t.states.shape[1] == 4:
                self.truth[t.scan] = t.states[0]
            else:
                self.stats.rejected["bad_shape"] += 1

    def forget_before(self, e: int, k: int) -> None:
        """Done with scan ``k`` of episode ``e``: drop the tracks and statuses of earlier
        scans (the next scan needs this one's statuses) and the truths of earlier scans, but
        the first :data:`~sensors.protocol.TRUTHS_NEAR` (the truth is every episode's, and the
        world may send the next episode's first window before this episode ends).  They were
        kept for the whole run: 2.3 kB a scan.

        A track dropped here was never taken: it came after the node fused its scan (``late``)
        or from a neighbour the scan did not enable (``not_enabled``, as the fusion centre
        counts a measurement it did not ask for); each is counted.  Before, they went
        uncounted (a forged track of a scan already fused was neither fused nor counted)."""
        for key in [key for key in self.tracks if key[1:] < (e, k)]:
            n, scan = key[0], key[1:]
            why = "late" if n in self.wanted.get(scan, ()) else "not_enabled"
            self.stats.rejected[why] += len(self.tracks.pop(key))
        for scan in [scan for scan in self.wanted if scan < (e, k)]:
            del self.wanted[scan]
        self.statuses.difference_update([s for s in self.statuses if s[1:] < (e, k)])
        for old in [j for j in self.truth if TRUTHS_NEAR < j < k]:
            del self.truth[old]

    def _outside(self, episode: int, scan: int) -> str | None:
        """Why a track or status of ``(episode, scan)`` is not kept: ``bad_scan`` outside the
        run, ``wrong_scan`` beyond the scan after the node's own (in lockstep no peer gets
        further: it waits for this node's status of its scan); None when it is kept."""
        if not (0 <= episode < self.episodes and 1 <= scan <= self.scans):
            return "bad_scan"
        e, k = self.at
        nxt = (e, k + 1) if k < self.scans else (e + 1, 1)
        return "wrong_scan" if (episode, scan) > nxt else None

    def _status(self, s: Sample) -> None:
        try:
            st = msg.decode_as(s.payload, msg.Status)
            node, _ = msg.parse_peer_key(s.key)
        except msg.WireError as exc:
            self.stats.rejected[exc.reason] += 1
            return
        except ValueError:
            self.stats.rejected["bad_key"] += 1
            return
        if st.node_id != node:
            self.stats.rejected["key_mismatch"] += 1
            return
        if (why := self._outside(st.episode, st.scan)) is not None:
            self.stats.rejected[why] += 1
            return
        self.statuses.add((node, st.episode, st.scan))

    def wait(
        self,
        done: Callable[[], bool],
        deadline: float,
        stop: threading.Event,
        heartbeat: Callable[[], None],
    ) -> bool:
        """Drain until ``done()`` (True) or the deadline / stop (False)."""
        while True:
            self.drain()
            if done():
                return True
            if stop.is_set() or time.monotonic() > deadline:
                return False
            heartbeat()
            s = self.status_sub.recv(timeout=0.001)  # sleeps until a status or 1 ms
            if s is not None:
                self._status(s)

    def each(
        self,
        nodes: Collection[str],
        have: Container[tuple[str, int, int]],
        episode: int,
        scan: int,
        timeout_s: float,
        stop: threading.Event,
        heartbeat: Callable[[], None],
        give_up: Callable[[], bool] | None = None,
    ) -> bool:
        """Wait until every node of ``nodes`` has its ``(node, episode, scan)`` entry in
        ``have`` (statuses or tracks) or has left (its liveliness token is gone), or
        ``give_up()`` (the world gone: no track made from its truth will come)."""
        return self.wait(
            lambda: all((n, episode, scan) in have or n not in self.alive for n in nodes)
            or (give_up is not None and give_up()),
            time.monotonic() + timeout_s,
            stop,
            heartbeat,
        )

    def close(self) -> None:
        for sub in (self.status_sub, self.truth_sub, *self.track_subs):
            sub.close()
        self.live_sub.close()


def _truth_or(inbox: _Inbox, k: int, give_up: Callable[[], bool]) -> bool:
    """Scan ``k``'s truth has come, or ``give_up()`` (the world is gone)."""
    return _has_truth(inbox, k) or give_up()


def _has_truth(inbox: _Inbox, k: int) -> bool:
    return k in inbox.truth


class _Passing:
    """``(node, episode, scan) in self``: a kept track of that node and scan passes
    ``verdict`` (the engine's, for the planned scan); :meth:`take` the first that does, the
    others counted."""

    def __init__(
        self,
        tracks: dict[tuple[str, int, int], list[msg.LocalTrack]],
        verdict: Callable[[msg.LocalTrack], str | None],
    ):
        self.tracks, self.verdict = tracks, verdict
        self.seen: dict[int, str | None] = {}  # id of a candidate -> its verdict

    def _why(self, m: msg.LocalTrack) -> str | None:
        if id(m) not in self.seen:
            self.seen[id(m)] = self.verdict(m)
        return self.seen[id(m)]

    def __contains__(self, key: object) -> bool:
        cands = self.tracks.get(key, []) if isinstance(key, tuple) else []
        return any(self._why(m) is None for m in cands)

    def take(self, key: tuple[str, int, int], rejected: Counter[str]) -> msg.LocalTrack | None:
        chosen = None
        for m in self.tracks.pop(key, ()):
            why = self._why(m)
            if why is not None:
                rejected[why] += 1
            elif chosen is None:
                chosen = m
            else:
                rejected["duplicate"] += 1
        return chosen


def run(
    sc: Scenario,
    node_id: str,
    metrics: Sequence[str],
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
) -> PeerStats:
    """Serve every metric's episode as peer node ``node_id`` (see the module docstring)."""
    model = build_model(sc)
    net, ids = sc.network, model.sensor_ids
    me = ids.index(node_id)
    nbrs = neighbours(sc.fusion, ids)[me]
    # the kind's scan logic for this node: the shared decision, this node's fusion
    engine = ScanEngine(sc, metrics, model=model, nodes=(me,))
    side = SensorSide(engine, me)
    stats = PeerStats()
    inbox = _Inbox(
        bus, run_id, node_id, [ids[n] for n in nbrs], stats, len(metrics), model.scans
    )
    manager = ManagerWatch(bus, run_id, manager_grace_s(net), manager_appear_s(net))
    token = bus.declare_token(msg.alive_key(run_id, "sensor", node_id))
    heartbeat = Heartbeat(bus, clock, run_id, "sensor", node_id, net.heartbeat_s, config_id(sc))
    keys = {
        "meas": msg.measurement_key(run_id, node_id),
        "track": msg.peer_track_key(run_id, node_id),
        "status": msg.peer_status_key(run_id, node_id),
    }
    last = [0]
    # a world gone for good: a scan's waits for the truth and for the tracks made from it end
    # after WORLD_GONE_WAIT_S (a node without the truth publishes its Status without a track
    # at once, and no peer times it out)
    returns = world_returns(sc)

    def beat() -> None:
        heartbeat.tick(last[0], stats.rejected)

    def world_gone(since: float) -> bool:
        return (
            not returns
            and msg.WORLD_ID not in inbox.alive
            and time.monotonic() - since > WORLD_GONE_WAIT_S
        )

    try:
        # start: every peer, the world, the monitor (and the recorder) up, so that every node
        # starts with the same members and nothing goes unrecorded
        everyone = {*ids, "world", "manager", *(("recorder",) if net.record else ())}
        # (or the monitor ended the run already: a node of another config refused, say)
        if not inbox.wait(
            lambda: inbox.alive >= everyone or manager.left,
            time.monotonic() + net.ready_timeout_s,
            stop,
            beat,
        ):
            return stats
        members = set(ids)
        prev: tuple[int, int] | None = None
        for e in range(len(metrics)):
            engine.start_episode(e)
            for k in range(1, model.scans + 1):
                if stop.is_set() or manager.left:
                    return stats
                inbox.at = (e, k)
                if prev is not None:
                    pe, pk = prev
                    others = members - {node_id}
                    inbox.each(others, inbox.statuses, pe, pk, net.scan_timeout_s, stop, beat)
                    if stop.is_set():  # the members are not known: the scan is not begun
                        return stats
                    members = {node_id} | {n for n in others if (n, pe, pk) in inbox.statuses}
                plan = engine.decide(k, engine.unavailable(frozenset(ids) - members))
                t_k = k * model.T
                got: dict[str, Any] = {}
                # one WORLD_GONE_WAIT_S a scan while the world is gone, from here: the waits
                # for the truth and for the neighbours' tracks each took one (1 s a scan)
                t0 = time.monotonic()
                if node_id in plan.enabled:
                    if inbox.wait(
                        partial(_truth_or, inbox, k, partial(world_gone, t0)),
                        t0 + net.scan_timeout_s,
                        stop,
                        beat,
                    ) and _has_truth(inbox, k):
                        tr = side.respond(e, k, plan, truth=inbox.truth[k])
                        assert isinstance(tr, Tracked)  # peer rules fuse local tracks
                        bus.publish(
                            keys["meas"],
                            msg.encode(
                                msg.LocalTrack(
                                    sensor_id=node_id,
                                    scan=k,
                                    t=t_k,
                                    x=tr.x,
                                    P=tr.P,
                                    x_prior=tr.x_prior,
                                    P_prior=tr.P_prior,
                                    t_sent_ns=clock.now_ns(),
                                    episode=e,
                                )
                            ),
                        )
                        stats.tracks_sent += 1
                        got[node_id] = tr
                want = [ids[j] for j in plan.subset if j in nbrs and ids[j] in members]
                passing = _Passing(inbox.tracks, engine.verdict)
                give_up = partial(world_gone, t0)
                inbox.each(want, passing, e, k, net.scan_timeout_s, stop, beat, give_up)
                if stop.is_set():  # cut by the stop: not the scan the network would have fused
                    return stats
                for n in want:
                    m = passing.take((n, e, k), stats.rejected)
                    if m is not None:
                        got[n] = m
                inbox.wanted[(e, k)] = frozenset(want)
                out = engine.report(plan, engine.fuse(plan, got), got)
                fused = out.tracks[0][1]
                stats.tracks_fused += len(out.fused)
                stats.scans += 1
                last[0] = k
                now = clock.now_ns()
                bus.publish(
                    keys["track"],
                    msg.encode(
                        msg.Track(
                            scan=k,
                            t=t_k,
                            x=fused.x,
                            P=fused.P,
                            t_sent_ns=now,
                            episode=e,
                            node_id=node_id,
                        )
                    ),
                )
                bus.publish(
                    keys["status"],
                    msg.encode(
                        msg.Status(
                            scan=k,
                            t=t_k,
                            enabled=plan.enabled,
                            trace_P=out.trace_P,
                            trace_Pd=out.trace_Pd,
                            value=out.value,
                            t_sent_ns=now,
                            episode=e,
                            fused=out.fused,
                            failed=tuple(n for n in ids if n not in members),
                            node_id=node_id,
                        )
                    ),
                )
                inbox.forget_before(e, k)
                prev = (e, k)
        # the last status must reach the others before this node leaves
        beat()
        inbox.wait(lambda: manager.left, time.monotonic() + net.ready_timeout_s, stop, beat)
    finally:
        # what it refused to the end, for the monitor's network.json (it lingers for this)
        heartbeat.tick(last[0], stats.rejected, now=True)
        stats.manager_lost = manager.left_badly(stop)
        token.undeclare()
        manager.close()
        inbox.close()
    return stats
