"""The world's loop: publish ``Truth(k)`` for the scans of the run.

The trajectory is a pure function of the scenario and its seed
(:func:`covnet.covariance_control.model.truth_trajectory`) and does not depend on the commands, so
for a run of at most :data:`~covnet.wire.messages.TRUTH_UPFRONT_MAX_SCANS` scans the world publishes
the
truth of every scan once, as soon as every sensor (and the recorder, when there is one) is alive,
and again whenever a sensor (re)joins; it never hears a command (one delivery fewer per scan: the
paper run goes from ~398 to ~450 scans/s).  The sensors keep that truth for the whole run (every
metric's episode uses the same trajectory) and only ever measure a scan they were commanded
for.  A longer run is paced by the manager's scan tick instead, in lockstep and in real time
alike: on ``Command(k)`` the world publishes ``Truth(k)`` .. ``Truth(k+16)`` unless the previous
window already covered ``k`` and no sensor has joined since (on the command of a window's last
scan ``k``, the next window ``Truth(k+1)`` .. ``Truth(k+17)``, a scan ahead); until its first
command it also follows the sensors' heartbeats (a world restarted while a command was in
flight sends that scan's truth).  It ends on ``stop`` or when the manager it has seen leaves.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Iterator
from typing import Any

import numpy as np

from covnet.clock import Clock
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.model import Model, build_model, truth_trajectory
from covnet.processes.node_kit import (
    Heartbeat,
    ManagerWatch,
    config_id,
    manager_appear_s,
    manager_grace_s,
    serve_commands,
)
from covnet.wire import messages as msg
from covnet.wire.bus import Bus

TARGET_IDS = ("T1",)
TRUTH_WINDOW = 16  # scans of truth published at once, ahead of their commands


def run(sc: Scenario, bus: Bus, run_id: str, clock: Clock, stop: threading.Event) -> Counter[str]:
    """Serve truth until ``stop`` is set; returns counters (``published``, and
    ``rejected:<reason>`` for every malformed or out-of-range command dropped)."""
    model = build_model(sc)
    if sc.surveillance is not None:  # every target that ever exists: (scans, n, 4), NaN absent
        # start-up: the surveillance world only for configs with surveillance
        from covnet.covariance_control import surveillance

        sm = surveillance.build(sc)
        truth, ids = np.swapaxes(sm.truth, 0, 1), sm.truth_ids
    elif sc.multitarget:  # every target's truth: (scans, T, 4)
        # start-up: the many-target model only for configs with targets
        from covnet.covariance_control import targets

        tm = targets.build(sc)
        truth, ids = np.swapaxes(targets.truth_trajectories(tm), 0, 1), tm.target_ids
    else:
        truth, ids = truth_trajectory(model)[:, None, :], TARGET_IDS
    counts: Counter[str] = Counter()
    publish = _TruthPublisher(bus, run_id, model, truth, counts, ids)
    if not sc.fusion.has_centre:
        _serve_peers(sc, bus, run_id, clock, stop, publish)
        return counts
    if model.scans <= msg.TRUTH_UPFRONT_MAX_SCANS:
        _serve_upfront(sc, bus, run_id, clock, stop, publish)
        return counts
    window = [0, -1]  # the first and last scans whose truth went out with the last window
    # a sensor that (re)joins mid-run has missed the window: the next command starts a new one
    joins = bus.watch_liveliness(msg.alive_keyexpr(run_id, "sensor"))
    # until its first command, the sensors' heartbeats (the last command each took): a world
    # restarted while a command was in flight sends that scan's truth, which its sensors
    # wait for (else the scan waited scan_timeout_s and fused nothing)
    beats: list[Any] = [bus.subscribe(msg.heartbeat_keyexpr(run_id))]

    def follow_heartbeats() -> None:
        for k in _sensor_scans(beats[0], counts) if beats else ():
            if 1 <= k <= model.scans and not window[0] <= k <= window[1]:
                window[:] = [k, publish(k, k + TRUTH_WINDOW)]

    def handle(cmd: msg.Command) -> bool:
        if not 1 <= cmd.scan <= model.scans:
            counts["rejected:bad_scan"] += 1
            return False
        if beats:  # the commands lead from here
            beats.pop().close()
        # Truth goes out a window of scans ahead (the trajectory does not depend on the
        # commands): a sensor wakes for truth once per window, not once per scan, and holds
        # the truth when its command comes.  The next window goes out with the command of a
        # window's last scan, one scan ahead (it sent that last scan again: 17 truths a 16
        # scans); a new one when a command leaves the last (or the scans start again: the
        # next metric's episode).
        k0 = cmd.scan
        while (ev := joins.try_recv()) is not None:
            if ev.alive:
                window[:] = [0, -1]
        if k0 == window[1] < model.scans:
            window[:] = [k0 + 1, publish(k0 + 1, k0 + 1 + TRUTH_WINDOW)]
        elif not window[0] <= k0 <= window[1]:
            window[:] = [k0, publish(k0, k0 + TRUTH_WINDOW)]
        return True

    try:
        serve_commands(
            bus, run_id, clock, stop, sc.network, "world", "world", counts, handle,
            idle=follow_heartbeats, config=config_id(sc),
        )  # fmt: skip
    finally:
        joins.close()
        for sub in beats:
            sub.close()
    return counts


def _sensor_scans(beats: Any, counts: Counter[str]) -> Iterator[int]:
    """The scans the sensors' heartbeats waiting in subscription ``beats`` carry (a sensor's:
    the last command it took; a peer node's: the last scan it finished), a malformed one
    counted as ``rejected:<reason>``: where a restarted world learns the nodes are."""
    while (h := beats.try_recv()) is not None:
        try:
            hb = msg.decode_as(h.payload, msg.Heartbeat)
        except msg.WireError as exc:
            counts[f"rejected:{exc.reason}"] += 1
            continue
        if hb.role == "sensor":
            yield hb.scan


class _TruthPublisher:
    """``publish(k0, hi)`` publishes ``Truth(k)`` for ``k0 <= k <= min(hi, scans)`` and returns
    the last scan published (counted as ``published``); ``truth`` is ``(scans, T, 4)``, row
    ``t`` of a scan the state of target ``target_ids[t]`` (NaN rows: a surveillance target
    absent at the scan, left out of its message)."""

    def __init__(
        self,
        bus: Bus,
        run_id: str,
        model: Model,
        truth: np.ndarray,
        counts: Counter[str],
        target_ids: tuple[str, ...] = TARGET_IDS,
    ) -> None:
        self.bus, self.model, self.truth, self.counts = bus, model, truth, counts
        self.target_ids = target_ids
        self.key = msg.truth_key(run_id)

    def __call__(self, k0: int, hi: int) -> int:
        hi = min(hi, self.model.scans)
        T, truth = self.model.T, self.truth
        for k in range(k0, hi + 1):
            X, ids = truth[k - 1], self.target_ids
            here = np.all(np.isfinite(X), axis=1)
            if not here.all():  # surveillance: only the targets present at the scan
                X, ids = X[here], tuple(t for t, h in zip(ids, here, strict=True) if h)
            tr = msg.Truth(scan=k, t=k * T, target_ids=ids, states=X)
            self.bus.publish(self.key, msg.encode(tr))
            self.counts["published"] += 1
        return hi


def _serve_upfront(
    sc: Scenario,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    publish: _TruthPublisher,
) -> None:
    """A run of at most ``TRUTH_UPFRONT_MAX_SCANS`` scans: every scan's truth once every sensor
    (and the recorder, which records it) is alive, again when a sensor (re)joins."""
    live = bus.watch_liveliness(msg.alive_keyexpr(run_id))  # every role
    manager = ManagerWatch(
        bus, run_id, manager_grace_s(sc.network), manager_appear_s(sc.network)
    )
    token = bus.declare_token(msg.alive_key(run_id, "world", "world"))
    heartbeat = Heartbeat(
        bus, clock, run_id, "world", "world", sc.network.heartbeat_s, config_id(sc)
    )
    wanted = _first_truth_waits_for(sc, run_id)
    alive: set[str] = set()
    sent = False
    try:
        while not stop.is_set() and not manager.left:
            heartbeat.tick(0)
            ev = live.recv(timeout=sc.network.heartbeat_s / 2)
            joined = False
            while ev is not None:
                if ev.key in wanted:
                    if ev.alive and ev.key not in alive:
                        joined = True
                    (alive.add if ev.alive else alive.discard)(ev.key)
                ev = live.try_recv()
            if alive >= wanted and (not sent or joined):
                publish(1, publish.model.scans)  # first time, or a (re)joined sensor needs it
                sent = True
    finally:
        manager.note_lost(publish.counts, stop)
        token.undeclare()
        manager.close()
        live.close()


def _first_truth_waits_for(sc: Scenario, run_id: str) -> set[str]:
    """The liveliness tokens the first truth waits for: every sensor's and the recorder's,
    which records it."""
    wanted = {msg.alive_key(run_id, "sensor", sid) for sid in sc.sensor_ids}
    if sc.network.record:
        wanted.add(msg.alive_key(run_id, "recorder", "recorder"))
    return wanted


def _serve_peers(
    sc: Scenario,
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    publish: _TruthPublisher,
) -> None:
    """Peer mode (no commands): the first window of truth goes out once every sensor (and the
    recorder, which records it: without it the first truths were missing from the recording)
    is up, the next ones ahead of the scans the peer nodes' statuses show they have reached.

    Until its first status a world also reads the nodes' heartbeats (each says the last scan
    its node finished, the truth is the same in every episode): a world restarted after the
    nodes left its last window learns where they are from them, within a heartbeat period,
    where it sent scans 1-17 and waited for a status that no node could make without the
    truth it waited for (``scan_timeout_s``, one scan fused without truth)."""
    model, counts = publish.model, publish.counts
    status_sub = bus.subscribe(msg.peer_keyexpr(run_id, "status"))
    beats: Any = bus.subscribe(msg.heartbeat_keyexpr(run_id))
    live = bus.watch_liveliness(msg.alive_keyexpr(run_id))  # every role
    wanted = _first_truth_waits_for(sc, run_id)
    manager = ManagerWatch(
        bus, run_id, manager_grace_s(sc.network), manager_appear_s(sc.network)
    )
    token = bus.declare_token(msg.alive_key(run_id, "world", "world"))
    heartbeat = Heartbeat(
        bus, clock, run_id, "world", "world", sc.network.heartbeat_s, config_id(sc)
    )
    alive: set[str] = set()
    window = [0, -1]
    last_scan = 0

    def publish_from(k0: int) -> None:
        window[:] = [k0, publish(k0, k0 + TRUTH_WINDOW)]

    def after(done: int) -> int:
        """The scan whose truth the nodes need next, after finishing scan ``done``."""
        return done + 1 if done < model.scans else 1

    def follow_heartbeats() -> None:
        for done in _sensor_scans(beats, counts):
            if done > 0 and not window[0] <= (need := after(done)) <= window[1]:
                publish_from(need)

    try:
        while not stop.is_set() and not manager.left:
            rejected = {k[9:]: v for k, v in counts.items() if k.startswith("rejected:")}
            heartbeat.tick(last_scan, rejected)
            while (ev := live.try_recv()) is not None:
                (alive.add if ev.alive else alive.discard)(ev.key)
            if window[1] < 0 and alive >= wanted:
                publish_from(1)
            if beats is not None and window[1] >= 0:
                follow_heartbeats()
            s = status_sub.recv(timeout=sc.network.heartbeat_s / 2)
            if s is None or window[1] < 0:
                continue
            try:
                st = msg.decode_as(s.payload, msg.Status)
            except msg.WireError as exc:
                counts[f"rejected:{exc.reason}"] += 1
                continue
            if beats is not None:  # the statuses lead from here
                beats.close()
                beats = None
            need = after(st.scan)
            last_scan = st.scan
            if not window[0] <= need <= window[1]:
                publish_from(need)
    finally:
        manager.note_lost(counts, stop)
        token.undeclare()
        manager.close()
        live.close()
        status_sub.close()
        if beats is not None:
            beats.close()
