"""The fusion manager's loop: predict -> allocate -> command -> collect -> fuse -> publish.

One *episode* per allocation metric (the paper compares three on the same scenario); in each,
per scan ``k``::

    1. x⁻, P⁻ = predict(x, P)
    2. D = argmin over feasible subsets of f(P_i, P_d(t_k)); failed sensors are infeasible
    3. publish Command(k, enabled = D) on the key that names D, so that only the enabled
       sensors (and the recorder) receive it (sensors take Truth(k) the world sent); in
       lockstep, then scan k-1's report (step 6): the next command is what the network waits
       for, the report only the recorder and observers read
    4. collect Measurement(k) from each enabled sensor until all arrived, a sensor failed, or
       the deadline passed (lockstep: ``network.scan_timeout_s``; real time: ``t_k +
       deadline_fraction * T``).  Anything malformed, from the wrong key, for another scan or
       from a sensor that was not enabled is counted by reason and dropped, never fused.
    5. fuse (sequential updates, ascending sensor index)
    6. report scan k: log it (estimates, NEES), publish Track(k) and Status(k), call the
       status and progress hooks; at once in real time, in lockstep just after Command(k+1)
       (and at the end of an episode, and when the loop stops)

The steps are the functions of :mod:`covnet.model`, the same ones ``covnet run`` calls, so a
lockstep network run reproduces the in-process run bit for bit.  The loop takes its bus, clock
and stop event from the caller: a test runs it in a thread over ``InMemoryBus``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from covnet import messages as msg
from covnet.bus import Bus
from covnet.clock import Clock
from covnet.config import NetworkSpec, Scenario
from covnet.core.allocation import Allocation
from covnet.core.fusion import LocalTrack
from covnet.core.gaussian import Gaussian, is_spd
from covnet.core.kalman import gain_and_covariance, nees
from covnet.core.oosm import ReFilterBuffer
from covnet.decentral import Mirror, decide_rule, fuse_tracks, measurement_from_track
from covnet.model import (
    Model,
    build_model,
    decide,
    fuse,
    initial_estimate,
    predict_cov,
    predict_step,
    truth_trajectory,
    usable_measurement,
)
from covnet.runtime_stats import NetStats
from covnet.simulate import MetricRun
from manager.membership import Membership

WORLD_ID = "world"
RECORDER_ID = "recorder"
MEMBERSHIP_POLL_S = 0.005
"""While measurements keep arriving, the longest time between two membership checks."""


class ManagerError(RuntimeError):
    """The network could not run (nodes never came up, the stop was requested, ...)."""


@dataclass
class EpisodeLog:
    """Rows of one episode, appended per scan; converted to a :class:`MetricRun` at the end."""

    metric: str
    enabled: list[np.ndarray] = field(default_factory=list)
    value: list[float] = field(default_factory=list)
    x_est: list[np.ndarray] = field(default_factory=list)
    P_post: list[np.ndarray] = field(default_factory=list)
    P_pred: list[np.ndarray] = field(default_factory=list)
    nees: list[float] = field(default_factory=list)
    decision_s: list[float] = field(default_factory=list)
    n_evaluated: list[int] = field(default_factory=list)
    fused_from: list[list[str]] = field(default_factory=list)
    failures: list[dict[str, Any]] = field(default_factory=list)

    def record(
        self,
        n_sensors: int,
        alloc: Allocation,
        pred: Gaussian,
        est: Gaussian,
        nees_value: float,
        decision_s: float,
        fused: list[str],
    ) -> None:
        """Append one scan: the allocation, the predicted and fused estimates, NEES, timing."""
        mask = np.zeros(n_sensors, dtype=bool)
        mask[list(alloc.subset)] = True
        self.enabled.append(mask)
        self.value.append(float(alloc.value))
        self.x_est.append(est.x)
        self.P_post.append(est.P)
        self.P_pred.append(pred.P)
        self.nees.append(nees_value)
        self.decision_s.append(decision_s)
        self.n_evaluated.append(alloc.n_evaluated)
        self.fused_from.append(fused)

    def as_run(self, n_sensors: int) -> MetricRun:
        n = len(self.value)
        return MetricRun(
            metric=self.metric,
            enabled=np.array(self.enabled, dtype=bool).reshape(n, n_sensors),
            value=np.array(self.value, dtype=np.float64),
            x_est=np.array(self.x_est, dtype=np.float64).reshape(n, 4),
            P_post=np.array(self.P_post, dtype=np.float64).reshape(n, 4, 4),
            P_pred=np.array(self.P_pred, dtype=np.float64).reshape(n, 4, 4),
            nees=np.array(self.nees, dtype=np.float64),
            decision_s=np.array(self.decision_s, dtype=np.float64),
            n_evaluated=np.array(self.n_evaluated, dtype=np.int64),
        )


@dataclass
class ManagerResult:
    """What the loop has done so far (live while it runs; final when :func:`run` returns)."""

    episodes: dict[str, EpisodeLog]
    stats: NetStats
    completed: bool = False
    error: str | None = None


StatusFn = Callable[[dict[str, Any]], None]


class _Loop:
    """The manager's state; only :func:`run` drives it."""

    def __init__(
        self, net: NetworkSpec, sensor_ids: tuple[str, ...], bus: Bus, run_id: str, clock: Clock
    ) -> None:
        self.net, self.bus, self.run_id, self.clock = net, bus, run_id, clock
        self.ids = sensor_ids
        self.members = Membership(
            expected=(*self.ids, WORLD_ID), failure_timeout_ns=int(net.failure_timeout_s * 1e9)
        )
        # the recorder must hear everything: wait for its token too (never allocated)
        self.wait_for = (*self.members.expected, RECORDER_ID) if net.record else ()
        self.stats = NetStats()
        # slow links (network.latency): a late message goes to on_late (re-filtered or
        # dropped, it says which); a sensor that measured on a stale command is fused too
        self.on_late: Callable[[Any], bool] | None = None
        self.accept_unsolicited = False
        self.meas_sub = bus.subscribe(msg.measurement_keyexpr(run_id))
        self.hb_sub = bus.subscribe(msg.heartbeat_keyexpr(run_id))
        self.live_sub = bus.watch_liveliness(msg.alive_keyexpr(run_id))
        self.token = bus.declare_token(msg.alive_key(run_id, "manager", "manager"))
        self.keys = {
            "cmd": msg.command_keyexpr(run_id),  # commands are counted under this one
            "track": msg.track_key(run_id),
            "status": msg.status_key(run_id),
        }

    # ---- bus helpers --------------------------------------------------------------------

    def publish(self, key: str, message: msg.Message, *, count_as: str | None = None) -> None:
        """Encode and publish ``message`` on ``key``; counted under ``count_as`` or ``key``."""
        payload = msg.encode(message)
        self.bus.publish(key, payload)
        self.stats.sent(count_as or key, len(payload))

    def publish_command(self, cmd: msg.Command) -> None:
        """Publish ``cmd`` on its own key (:func:`~covnet.messages.command_key`: zenoh takes
        it to the enabled sensors only); counted under ``keys["cmd"]``, every command's."""
        key = msg.command_key(self.run_id, cmd.enabled)
        self.publish(key, cmd, count_as=self.keys["cmd"])

    def poll_membership(self) -> None:
        """Drain liveliness events and heartbeats (non-blocking)."""
        now = self.clock.now_ns()
        while (ev := self.live_sub.try_recv()) is not None:
            try:
                role, node = msg.parse_alive_key(ev.key)
            except ValueError:
                self.stats.reject(ev.key, "bad_key")
                continue
            if role in ("sensor", "world", "recorder"):
                self.members.token(node, ev.alive, now)
        while (s := self.hb_sub.try_recv()) is not None:
            self.stats.received(s.key, len(s.payload))
            try:
                hb = msg.decode_as(s.payload, msg.Heartbeat)
            except msg.WireError as exc:
                self.stats.reject(s.key, exc.reason)
                continue
            if msg.heartbeat_key(self.run_id, hb.role, hb.node_id) != s.key:
                self.stats.reject(s.key, "key_mismatch")
                continue
            if hb.node_id in self.members.expected:
                self.members.heartbeat(hb.node_id, now)
            if hb.rejected:
                self.stats.node_rejected[hb.node_id] = dict(hb.rejected)

    def membership_changes(
        self, k: int, previous: frozenset[str]
    ) -> tuple[frozenset[str], list[dict[str, Any]]]:
        """The failed set at scan ``k`` and the failure/rejoin events since ``previous``
        (a failure carries when it was first seen, ``detected_ns``)."""
        self.poll_membership()
        failed = self.members.failed(self.clock.now_ns())
        events: list[dict[str, Any]] = []
        for sid in sorted((failed ^ previous) - {WORLD_ID}):
            event: dict[str, Any] = {
                "sensor": sid,
                "scan": k,
                "event": "failed" if sid in failed else "rejoined",
            }
            if sid in failed:
                event["detected_ns"] = self.members.down_since_ns(sid)
            events.append(event)
        return failed, events

    def traffic(self) -> tuple[int, int]:
        """Messages and bytes this manager has sent and received so far."""
        st = self.stats
        return (
            sum(st.recv_msgs.values()) + sum(st.sent_msgs.values()),
            sum(st.recv_bytes.values()) + sum(st.sent_bytes.values()),
        )

    def wait_ready(self, stop: threading.Event) -> None:
        deadline = time.monotonic() + self.net.ready_timeout_s
        while True:
            self.poll_membership()
            missing = [n for n in self.wait_for if n not in self.members.alive_tokens]
            missing = missing or self.members.missing_tokens()
            if not missing:
                return
            if stop.is_set():
                raise ManagerError("stopped before the network was ready")
            if time.monotonic() > deadline:
                raise ManagerError(f"nodes not alive after {self.net.ready_timeout_s} s: {missing}")
            ev = self.live_sub.recv(timeout=0.05)
            if ev is not None:
                role, node = msg.parse_alive_key(ev.key)
                if role in ("sensor", "world", "recorder"):
                    self.members.token(node, ev.alive, self.clock.now_ns())

    # ---- one scan -----------------------------------------------------------------------

    def collect(
        self,
        episode: int,
        k: int,
        waiting: set[str],
        deadline: float,
        stop: threading.Event,
        usable: Callable[[Any], bool],
        kind: type[msg.Measurement] | type[msg.LocalTrack] = msg.Measurement,
    ) -> dict[str, Any]:
        """Receive scan ``k``'s measurements (or, in the decentralized modes, local tracks:
        ``kind``) from the ``waiting`` sensors until all arrived, a sensor failed or the
        deadline passed (see module doc); ``usable`` is the scenario kind's test of a
        message's content. Every kind of manager collects this way.

        Membership (a waiting sensor that failed) is checked whenever a wait times out (at
        least every 0.05 s) and otherwise at most every :data:`MEMBERSHIP_POLL_S`: the scan
        began with a check, and a failed sensor sends nothing, so a wait then times out."""
        got: dict[str, Any] = {}
        next_poll = time.monotonic() + MEMBERSHIP_POLL_S
        while waiting:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or stop.is_set():
                self.stats.lost += len(waiting)
                break
            s = self.meas_sub.recv(timeout=min(0.05, remaining))
            if s is not None:
                self._take(s, episode, k, waiting, got, usable, kind)
                if time.monotonic() < next_poll:
                    continue
            next_poll = time.monotonic() + MEMBERSHIP_POLL_S
            self.poll_membership()
            dead = {sid for sid in waiting if not self.members.is_up(sid, self.clock.now_ns())}
            if dead:
                self.stats.lost += len(dead)
                waiting -= dead
        # anything else already queued for this scan (duplicates, strays) is judged now
        while (s := self.meas_sub.try_recv()) is not None:
            self._take(s, episode, k, set(), got, usable, kind)
        return got

    def _take(
        self,
        s: Any,
        episode: int,
        k: int,
        waiting: set[str],
        got: dict[str, Any],
        usable: Callable[[Any], bool],
        kind: type[msg.Measurement] | type[msg.LocalTrack] = msg.Measurement,
    ) -> None:
        self.stats.received(s.key, len(s.payload))
        try:
            m = msg.decode_as(s.payload, kind)
            key_sensor = msg.parse_measurement_key(s.key)
        except msg.WireError as exc:
            self.stats.reject(s.key, exc.reason)
            return
        except ValueError:
            self.stats.reject(s.key, "bad_key")
            return
        if key_sensor != m.sensor_id:
            self.stats.reject(s.key, "key_mismatch")
        elif (m.episode, m.scan) < (episode, k):
            self.stats.late += 1
            self.stats.meas_latency_ns.append(s.t_recv_ns - m.t_sent_ns)
            if self.on_late is not None and m.episode == episode and usable(m):
                if self.on_late(m):
                    self.stats.late_refiltered += 1
                else:
                    self.stats.late_dropped += 1
            else:
                self.stats.reject(s.key, "late")
        elif (m.episode, m.scan) != (episode, k):
            self.stats.reject(s.key, "wrong_scan")
        elif m.sensor_id in got:
            self.stats.reject(s.key, "duplicate")
        elif m.sensor_id not in waiting and not self.accept_unsolicited:
            self.stats.reject(s.key, "not_enabled")
        elif not usable(m):
            self.stats.reject(s.key, "bad_measurement")
        else:
            self.stats.unsolicited += m.sensor_id not in waiting
            got[m.sensor_id] = m
            waiting.discard(m.sensor_id)
            self.stats.meas_latency_ns.append(s.t_recv_ns - m.t_sent_ns)


class LateHandler:
    """One episode's out-of-sequence processing on slow links (``network.latency.late``):
    ``central``/``info`` keep a :class:`~covnet.core.oosm.ReFilterBuffer` of the last
    ``oosm_depth`` scans and filter every scan through it (the same updates as
    :func:`covnet.model.fuse`; a local track enters as the measurement whose information it
    added), so that a late message is re-filtered from its scan; ``ci`` and ``late: drop``
    drop late messages.  The loop counts which (``late_refiltered`` / ``late_dropped``)."""

    def __init__(self, sc: Scenario, model: Model) -> None:
        lat = sc.network.latency
        self.mode = sc.fusion.mode
        self.ids = model.sensor_ids
        self.inserted = False
        self.refiltered: list[str] = []  # "<sensor>:<scan>" since the last Status
        keep = lat.late == "oosm" and self.mode != "ci"
        self.buffer = ReFilterBuffer(model.F, model.Q, model.H, lat.oosm_depth) if keep else None

    def _measurement(self, m: Any) -> tuple[np.ndarray, np.ndarray]:
        if self.mode == "central":
            return m.z[0], m.R
        t = as_local_track(m)
        return measurement_from_track(t.post, t.prior)

    def insert(self, m: Any) -> bool:
        """A late message: True when it was re-filtered into its scan."""
        if self.buffer is None:
            return False
        try:
            done = self.buffer.insert(m.scan, self.ids.index(m.sensor_id), *self._measurement(m))
        except ValueError:  # that sensor's message of that scan is in already
            return False
        if done is not None:
            self.inserted = True
            self.refiltered.append(f"{m.sensor_id}:{m.scan}")
        return done is not None

    def take_refiltered(self) -> tuple[str, ...]:
        out, self.refiltered = tuple(self.refiltered), []
        return out

    def fuse(self, k: int, pred: Gaussian, got: dict[str, Any]) -> Gaussian:
        assert self.buffer is not None
        meas = [(self.ids.index(sid), *self._measurement(m)) for sid, m in got.items()]
        return self.buffer.step(k, meas, prior=pred).post


class CentreFilter:
    """One episode of the fusion centre's filter, in every mode (``central``, ``info``,
    ``ci``) and over ideal or slow links: the manager's loop and ``covnet replay`` both step
    it, so a replay recomputes exactly what the manager did.

    ``decide`` allocates scan ``k`` from ``P⁻`` (``ci``: against the local filters'
    covariances of :class:`~covnet.decentral.Mirror`, the only mode that needs them);
    ``insert_late`` takes a late message (slow links: :class:`LateHandler`); ``prior`` is scan
    ``k``'s prior once late messages were re-filtered; ``fuse`` fuses what arrived for scan
    ``k`` (``sensor id -> Measurement | LocalTrack``)."""

    def __init__(self, sc: Scenario, model: Model) -> None:
        self.model, self.fusion = model, sc.fusion
        self.ids = model.sensor_ids
        self.decentral = sc.fusion.mode in ("info", "ci")
        self.mirror = Mirror.start(model) if sc.fusion.rule == "ci" else None
        slow = not sc.network.latency.is_ideal(model.sensor_ids)
        self.late = LateHandler(sc, model) if slow else None

    def decide(
        self, P_pred: np.ndarray, k: int, metric: str, unavailable: frozenset[int]
    ) -> Allocation:
        if self.mirror is None:
            return decide(self.model, P_pred, k, metric, unavailable)
        P_loc = self.mirror.predicted(self.model)[1]
        return decide_rule(self.fusion, self.model, P_pred, P_loc, k, metric, unavailable)

    def insert_late(self, m: Any) -> bool:
        """A late message of an earlier scan: True when it was re-filtered into its scan."""
        return self.late is not None and self.late.insert(m)

    def prior(self, pred: Gaussian) -> Gaussian:
        """Scan ``k``'s prior: ``pred``, or the re-filtered one after late insertions."""
        late = self.late
        if late is not None and late.buffer is not None and late.inserted:
            late.inserted = False
            return late.buffer.predicted()
        return pred

    def fuse(
        self, k: int, pred: Gaussian, got: dict[str, Any], gains: _Gains | None = None
    ) -> Gaussian:
        """Scan ``k``'s posterior from ``pred`` and what arrived (``gains``: the central
        update's covariance work done ahead, used when it fits)."""
        if self.late is not None and self.late.buffer is not None:
            return self.late.fuse(k, pred, got)
        ids = self.ids
        if self.decentral:
            tracks = [(ids.index(sid), as_local_track(m)) for sid, m in got.items()]
            est = fuse_tracks(self.fusion, pred, tracks)
            if self.mirror is not None:
                self.mirror.advance(self.fusion, self.model, [j for j, _ in tracks])
                for j, tr in tracks:  # what the sensor reports is what it has
                    self.mirror.P_local[j] = tr.post.P
            return est
        return _fuse_with_gains(gains, self.model, pred, got, ids) or fuse(
            self.model, pred, [(ids.index(sid), m.z[0], m.R) for sid, m in got.items()]
        )


def usable_position(m: msg.Measurement) -> bool:
    """A covariance-control measurement the filter may fuse (see ``usable_measurement``)."""
    return usable_measurement(m.z, m.R)


def usable_track(m: msg.LocalTrack) -> bool:
    """A local track the fusion rules may take: a 4-state estimate with a symmetric positive
    definite posterior and prior covariance."""
    return m.x.shape == (4,) and is_spd(m.P) and is_spd(m.P_prior)


def as_local_track(m: msg.LocalTrack) -> LocalTrack:
    return LocalTrack(post=Gaussian(m.x, m.P), prior=Gaussian(m.x_prior, m.P_prior))


def run(
    sc: Scenario,
    metrics: list[str],
    bus: Bus,
    run_id: str,
    clock: Clock,
    stop: threading.Event,
    *,
    realtime: bool = False,
    on_ready: Callable[[], None] | None = None,
    on_status: StatusFn | None = None,
    on_progress: Callable[[ManagerResult, bool], None] | None = None,
) -> ManagerResult:
    """Run every metric's episode over the bus; returns what was done (also when stopped,
    with ``completed=False``, or when the network never came up, with ``error`` set).
    ``on_progress(result, episode_done)`` is called after every scan."""
    model = build_model(sc)
    fusion = sc.fusion
    decentral = fusion.mode in ("info", "ci")  # sensors publish local tracks, not measurements
    if fusion.mode == "peer":
        raise ManagerError("peer mode has no fusion manager: run manager.peer_monitor")
    # slow links (network.latency): late messages are re-filtered (or dropped), sensors that
    # measured on their missed-command fallback are fused too (see covnet.latency_sim)
    slow = not sc.network.latency.is_ideal(model.sensor_ids)
    loop = _Loop(sc.network, model.sensor_ids, bus, run_id, clock)
    ids = loop.ids
    net = sc.network
    result = ManagerResult({}, loop.stats)
    report = _Reporter(loop, model, result, on_status, on_progress)
    try:
        try:
            loop.wait_ready(stop)
        except ManagerError as exc:
            result.error = str(exc)
            return result
        if on_ready is not None:
            on_ready()
        t_loop = time.perf_counter_ns()
        for e, metric in enumerate(metrics):
            log = result.episodes[metric] = EpisodeLog(metric)
            est = initial_estimate(model, sc.filter.initial_estimate)
            centre = CentreFilter(sc, model)
            loop.on_late = centre.insert_late if slow else None
            loop.accept_unsolicited = slow
            t_origin = clock.now()
            failed_prev: frozenset[str] = frozenset()
            spec: _Speculation | None = None
            for k in range(1, model.scans + 1):
                if stop.is_set():
                    return result
                t_k = k * model.T
                if realtime:
                    _pace(clock, t_origin + (k - 1) * model.T, stop)
                t_core0 = time.perf_counter_ns()
                pred = predict_step(model, est)
                failed, events = loop.membership_changes(k, failed_prev)
                log.failures.extend(events)
                failed_prev = failed
                unavailable = frozenset(ids.index(s) for s in failed if s in ids)
                if spec is not None and spec.matches(k, pred.P, unavailable):
                    alloc, decision_s = spec.alloc, spec.decision_s  # decided ahead, exactly
                else:
                    t0 = time.perf_counter()
                    alloc = centre.decide(pred.P, k, metric, unavailable)
                    decision_s = time.perf_counter() - t0
                core_ns = time.perf_counter_ns() - t_core0
                enabled = tuple(ids[j] for j in alloc.subset)
                t_sent = clock.now_ns()
                cmd = msg.Command(scan=k, t=t_k, enabled=enabled, t_sent_ns=t_sent, episode=e)
                loop.publish_command(cmd)
                report.run()  # scan k-1's (lockstep)
                # while the sensors measure: decide scan k+1 assuming every enabled sensor's
                # measurement arrives (P does not depend on the measured values)
                gains = None
                if not decentral and not slow:
                    gains = _Gains.of(model, pred.P, alloc.subset)
                    spec = _speculate(model, gains.P_post, k + 1, metric, unavailable)
                if realtime:
                    deadline = time.monotonic() + net.deadline_fraction * model.T / _speed(clock)
                else:
                    deadline = time.monotonic() + net.scan_timeout_s
                if decentral:
                    got = loop.collect(
                        e, k, set(enabled), deadline, stop, usable_track, msg.LocalTrack
                    )
                else:
                    got = loop.collect(e, k, set(enabled), deadline, stop, usable_position)
                t_core1 = time.perf_counter_ns()
                pred = centre.prior(pred)  # re-filtered late messages change scan k's prior
                est = centre.fuse(k, pred, got, gains)
                loop.stats.core_ns.append(core_ns + time.perf_counter_ns() - t_core1)
                loop.stats.scans_done += 1
                loop.stats.loop_wall_ns = time.perf_counter_ns() - t_loop
                t_fused = clock.now_ns()
                loop.stats.scan_latency_ns.append(t_fused - t_sent)
                refiltered = centre.late.take_refiltered() if centre.late is not None else None
                report.hold(
                    _ScanReport(
                        episode=e,
                        metric=metric,
                        k=k,
                        t=t_k,
                        alloc=alloc,
                        decision_s=decision_s,
                        pred=pred,
                        est=est,
                        got=got,
                        failed=failed,
                        refiltered=refiltered,
                        latency_ns=t_fused - t_sent,
                    )
                )
                if realtime:
                    report.run()
            report.run()  # the episode's last scan
        result.completed = True
    finally:
        report.run()  # a stopped loop's last scan
        loop.token.undeclare()
    return result


@dataclass(frozen=True)
class _ScanReport:
    """What scan ``k`` of episode ``episode`` leaves to report (step 6 of the module doc)."""

    episode: int
    metric: str
    k: int
    t: float
    alloc: Allocation
    decision_s: float
    pred: Gaussian
    est: Gaussian
    got: dict[str, Any]
    failed: frozenset[str]
    refiltered: tuple[str, ...] | None
    latency_ns: int  # command published -> scan fused


class _Reporter:
    """Step 6 of the scan (module doc): :meth:`hold` keeps scan ``k``'s report, :meth:`run`
    makes it: the episode's log row (with NEES against the truth, which only the results
    use), ``Track(k)`` and ``Status(k)`` on the bus, and the ``on_status`` and
    ``on_progress`` hooks.  None of it is on the path to the next command."""

    def __init__(
        self,
        loop: _Loop,
        model: Model,
        result: ManagerResult,
        on_status: StatusFn | None,
        on_progress: Callable[[ManagerResult, bool], None] | None,
    ) -> None:
        self.loop, self.model, self.result = loop, model, result
        self.on_status, self.on_progress = on_status, on_progress
        self.truth = truth_trajectory(model)  # never sent to anyone
        self._held: _ScanReport | None = None

    def hold(self, r: _ScanReport) -> None:
        self._held = r

    def run(self) -> None:
        """Report the held scan, if any."""
        r, self._held = self._held, None
        if r is None:
            return
        loop, ids, clock, k = self.loop, self.loop.ids, self.loop.clock, r.k
        est = r.est
        track = msg.Track(
            scan=k, t=r.t, x=est.x, P=est.P, t_sent_ns=clock.now_ns(), episode=r.episode
        )
        loop.publish(loop.keys["track"], track)
        enabled = tuple(ids[j] for j in r.alloc.subset)
        status = msg.Status(
            scan=k,
            t=r.t,
            enabled=enabled,
            trace_P=float(np.trace(est.P)),
            trace_Pd=float(np.trace(self.model.desired(k))),
            value=float(r.alloc.value),
            t_sent_ns=clock.now_ns(),
            episode=r.episode,
            fused=tuple(sorted(r.got, key=ids.index)),
            failed=tuple(sorted(r.failed - {WORLD_ID})),
            refiltered=r.refiltered,
        )
        loop.publish(loop.keys["status"], status)
        log = self.result.episodes[r.metric]
        nees_k = nees(est, self.truth[k - 1])
        log.record(len(ids), r.alloc, r.pred, est, nees_k, r.decision_s, sorted(r.got))
        if self.on_status is not None:
            messages, n_bytes = loop.traffic()
            self.on_status(
                {
                    "metric": r.metric,
                    "episode": r.episode,
                    "scan": k,
                    "scans": self.model.scans,
                    "enabled": list(enabled),
                    "fused": sorted(r.got),
                    "failed": sorted(r.failed - {WORLD_ID}),
                    "trace_P": status.trace_P,
                    "trace_Pd": status.trace_Pd,
                    "latency_ms": r.latency_ns / 1e6,
                    "messages": messages,
                    "bytes": n_bytes,
                }
            )
        if self.on_progress is not None:
            self.on_progress(self.result, k == self.model.scans)


@dataclass(frozen=True)
class _Speculation:
    """The allocation of scan ``k``, decided while scan ``k-1``'s measurements were on their
    way, from the covariance the filter reaches if every enabled sensor's measurement arrives.
    It is used only when the real predicted covariance is bit for bit that one and the failed
    set is unchanged, so it never changes a decision, only when it is made."""

    k: int
    P_pred: np.ndarray
    unavailable: frozenset[int]
    alloc: Any
    decision_s: float

    def matches(self, k: int, P_pred: np.ndarray, unavailable: frozenset[int]) -> bool:
        return (
            self.k == k and self.unavailable == unavailable and np.array_equal(self.P_pred, P_pred)
        )


@dataclass(frozen=True)
class _Gains:
    """Scan ``k``'s Kalman updates when every enabled sensor's measurement arrives, computed
    while the sensors measure (neither the gains nor the covariances depend on the measured
    values): the gain of each sensor of ``subset`` (ascending index, the order of
    :func:`covnet.model.fuse`) and the posterior covariance, bit for bit those of
    :func:`covnet.model.fused_covariance` and of :func:`covnet.model.fuse`."""

    subset: tuple[int, ...]
    R: tuple[bytes, ...]  # each sensor's noise covariance the gains were computed with
    K: tuple[np.ndarray, ...]
    P_post: np.ndarray

    @staticmethod
    def of(model: Model, P_pred: np.ndarray, subset: tuple[int, ...]) -> _Gains:
        order = tuple(sorted(subset))
        P, gains = P_pred, []
        for j in order:  # = fused_covariance(model, P_pred, [(j, model.R[j]) ...]), step by step
            K, P = gain_and_covariance(P, model.H, model.R[j])
            gains.append(K)
        return _Gains(order, tuple(model.R[j].tobytes() for j in order), tuple(gains), P)


def _fuse_with_gains(
    gains: _Gains | None, model: Model, pred: Gaussian, got: dict[str, Any], ids: tuple[str, ...]
) -> Gaussian | None:
    """:func:`covnet.model.fuse` of ``got`` bit for bit, from the gains computed ahead, when
    they are the ones it needs (every enabled sensor's measurement arrived, with the noise
    covariance the gains assumed); None otherwise."""
    if gains is None or len(got) != len(gains.subset):
        return None
    ordered = sorted((ids.index(sid), m) for sid, m in got.items())
    if tuple(j for j, _ in ordered) != gains.subset or any(
        m.R.tobytes() != r for (_, m), r in zip(ordered, gains.R, strict=True)
    ):
        return None
    if not ordered:
        return pred
    H, x = model.H, pred.x
    for (_, m), K in zip(ordered, gains.K, strict=True):  # kalman.update's mean, in fuse's order
        z = m.z[0]
        x = x + K @ (z - H @ x)
    return Gaussian(x, gains.P_post)


def _speculate(
    model: Model, P_post: np.ndarray, k_next: int, metric: str, unavailable: frozenset[int]
) -> _Speculation | None:
    """Decide scan ``k_next`` from ``P_post``, scan ``k_next - 1``'s posterior covariance if
    every enabled sensor's measurement arrives."""
    if k_next > model.scans:
        return None
    t0 = time.perf_counter()
    P_next = predict_cov(model, P_post)
    alloc = decide(model, P_next, k_next, metric, unavailable)
    return _Speculation(k_next, P_next, unavailable, alloc, time.perf_counter() - t0)


def wait_for_nodes_to_leave(bus: Bus, run_id: str, timeout_s: float, stop: threading.Event) -> None:
    """After the run: wait (bounded) until no other node of the run is alive."""
    watch = bus.watch_liveliness(msg.alive_keyexpr(run_id))
    alive: set[str] = set()
    deadline = time.monotonic() + timeout_s
    first = True
    while time.monotonic() < deadline and not stop.is_set():
        ev = watch.recv(timeout=0.05)
        if ev is not None:
            if ev.alive:
                alive.add(ev.key)
            else:
                alive.discard(ev.key)
            first = False
            continue
        if not alive and not first:
            break
        first = False
    watch.close()


def _pace(clock: Clock, t: float, stop: threading.Event) -> None:
    """Wait until scenario time ``t`` on a wall clock, waking for ``stop``; a simulated
    clock just jumps."""
    if not hasattr(clock, "speed"):
        clock.sleep_until(t)
        return
    while not stop.is_set():
        remaining = (t - clock.now()) / _speed(clock)
        if remaining <= 0:
            return
        stop.wait(min(remaining, 0.05))


def _speed(clock: Clock) -> float:
    return float(getattr(clock, "speed", 1.0))
