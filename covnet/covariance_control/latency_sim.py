"""A scan loop over slow, lossy links, in simulated time (application-level emulation).

The network of ``network.latency`` (per sensor an uplink and a downlink
:class:`~covnet.core.delay.LinkSpec`, each drawing from its own stream of the seed) between the
sensors and a fusion centre, with the real-time protocol of ``covnet up --realtime`` (``T`` the
period, ``δ`` the ``network.deadline_fraction``, ``t_k = k T``, ``d_k = t_k + δ T`` the
deadline of scan k)::

    at t_k    the centre decides scan k (from what it had fused by d_{k-1}) and sends
              Command(k) down every link
    on receipt of Command(k) at a sensor (time a):
              older than its newest command: stale, ignored;
              scans it never got a command for (lost or overtaken) are filled by
              ``missed_command``: keep_last (its newest command's on/off), off or on, measured
              now (so late);
              if enabled: it measures scan k (noise stream (j, k)) and sends at a
    at d_k    the centre: (1) late messages that arrived in (d_{k-1}, d_k] (scans < k):
              re-filtered from their scan (``late: oosm``, exact, up to ``oosm_depth`` scans
              back, older ones dropped) or dropped (``late: drop``); (2) fuses scan k's
              messages that arrived by d_k

So a measurement is on time when its command's delay plus its own delay is at most ``δ T``.
A message lost by its link never arrives.  The centre fuses what it received, whoever sent it
(it knows what each sensor did from what arrives: one that measured on its fallback is fused
too).  With ideal links everything arrives on time and the loop is exactly the plain one
(:func:`covnet.covariance_control.simulate.run_metric`: the same bits for ``central``).

Fusion modes: ``central`` (measurements); ``info`` (local tracks; a track's new information
``(Y⁺ − Y⁻, y⁺ − y⁻) = (Hᵀ R⁻¹ H, Hᵀ R⁻¹ z)`` is the measurement's, so the centre recovers
``R = (H ΔY Hᵀ)⁻¹``, ``z = R H Δy`` and filters those: late tracks are re-filtered exactly
like late measurements); ``ci`` (covariance intersection has no exact out-of-sequence update:
late tracks are dropped and counted).  Peer mode has no centre and is not simulated here.

``allocation.account_for_loss``: the decision scales sensor ``j``'s information by its
probability ``p_j`` of delivering on time (command and measurement both arrive, within ``δ T``
together; estimated once from ``20 000`` draws of a dedicated stream per link), i.e. it
allocates on the *expected* information ``Σ p_j J_j`` (``ci``: each local track's expected
information ``Y⁻ + p_j (Y⁺ − Y⁻)``); the fusion itself uses what arrives.
"""

from __future__ import annotations

import heapq
import itertools
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from covnet.core.delay import LinkSpec, LinkState, link_stream
from covnet.core.oosm import ReFilterBuffer
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.decentral import Mirror, decide_rule
from covnet.covariance_control.fusion_rules import FusionRule, rule_for
from covnet.covariance_control.model import (
    Model,
    build_model,
    decide,
    initial_estimate,
    measure,
    predict_step,
    truth_trajectory,
)
from covnet.covariance_control.simulate import MetricRun, RunRows, TargetRows, TargetsRun
from covnet.latency_bus import DOWN, UP

PROBABILITY_DRAWS = 20_000
_PROB_STREAM_OFFSET = 1_000  # link indices of the delivery-probability estimate's own streams


@dataclass
class LatencyCounts:
    """What the links did in one run (summed over scans)."""

    commanded: int = 0  # sensors enabled by the centre's commands
    commands_missed: int = 0  # (sensor, scan) whose command was late or lost at t_k
    measured: int = 0  # measurements (or tracks) sensors sent
    unsolicited: int = 0  # ... by a sensor not enabled for that scan (a stale command)
    on_time: int = 0  # fused at their own scan's deadline
    late_refiltered: int = 0  # late, re-filtered from their scan (OOSM)
    late_dropped: int = 0  # late and dropped (policy drop, too old for the buffer, or CI)
    lost: int = 0  # never arrived
    deadline_misses: int = 0  # scans where something sent for them was not fused on time
    per_scan_fused: list[int] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k != "per_scan_fused"}


def link_specs(sc: Scenario) -> tuple[list[LinkSpec], list[LinkSpec]]:
    """Per sensor (table order) the uplink and downlink specs."""
    lat = sc.network.latency
    return (
        [lat.link(s, "uplink") for s in sc.sensor_ids],
        [lat.link(s, "downlink") for s in sc.sensor_ids],
    )


def _delays(link: LinkSpec, rng: np.random.Generator) -> np.ndarray:
    """:data:`PROBABILITY_DRAWS` one-way delays of ``link`` (``inf`` where lost)."""
    d = link.delay.sample(rng, PROBABILITY_DRAWS)
    if link.jitter_s > 0:
        d = d + link.jitter_s * rng.standard_normal(PROBABILITY_DRAWS)
    lost = rng.random(PROBABILITY_DRAWS) < link.loss
    return np.where(lost, np.inf, np.maximum(d, 0.0))


def delivery_probabilities(sc: Scenario) -> np.ndarray:
    """``p_j = P(down_j + up_j <= δ T)``, lost messages never arriving (module docstring)."""
    horizon = sc.network.deadline_fraction * sc.period_s
    up, down = link_specs(sc)
    p = []
    for j, (u, dn) in enumerate(zip(up, down, strict=True)):
        i = _PROB_STREAM_OFFSET + j
        total = _delays(dn, link_stream(sc.seed, i, DOWN)) + _delays(u, link_stream(sc.seed, i, UP))
        p.append(float(np.mean(total <= horizon)))
    return np.array(p)


def loss_aware_model(model: Model, p: np.ndarray) -> Model:
    """``model`` whose allocation uses the expected gains ``p_j J_j`` (a sensor that never
    delivers gets a tiny gain, so the plan stays valid)."""
    gains = np.maximum(p, 1e-12)[:, None, None] * model.gains
    return replace(model, gains_given=gains, plans={}, _derived={})


def _as_measurement(rule: FusionRule, payload: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(z, R)`` the buffer filters for a received message (a rule that re-filters late
    messages: a measurement as is, a local track's information)."""
    zr = rule.late_measurement(payload)
    assert zr is not None
    return zr


def run_latency(
    sc: Scenario, metric: str, model: Model | None = None
) -> tuple[MetricRun, LatencyCounts]:
    """The scan loop of the module docstring for the fusion centre of ``sc.fusion.mode`` (any
    rule of the registry)."""
    if sc.fusion.mode == "peer":
        raise ValueError("fusion.mode: peer has no fusion centre; latency runs need one")
    rule = rule_for(sc.fusion)
    model = model or build_model(sc)
    lat = sc.network.latency
    T, delta = model.T, sc.network.deadline_fraction
    Ns, N = len(model.sensor_ids), model.scans
    truth = truth_trajectory(model)
    up_specs, down_specs = link_specs(sc)
    up = [LinkState(s, link_stream(sc.seed, j, UP)) for j, s in enumerate(up_specs)]
    down = [LinkState(s, link_stream(sc.seed, j, DOWN)) for j, s in enumerate(down_specs)]
    p_deliver = delivery_probabilities(sc) if sc.allocation.account_for_loss else None
    alloc_model = model
    if p_deliver is not None and rule.information_form:
        alloc_model = loss_aware_model(model, p_deliver)
    counts = LatencyCounts()
    est = initial_estimate(model, sc.filter.initial_estimate)
    buffer = ReFilterBuffer(model.F, model.Q, model.H, lat.oosm_depth)
    sensors = [_Sensor(model, sc.filter.initial_estimate) for _ in range(Ns)]
    mirror = Mirror.start(model)
    commands: list[tuple[float, int, int, int, bool]] = []  # heap: (arrival, seq, j, scan, on)
    seq = itertools.count()
    pending: list[tuple[float, int, int, int, Any]] = []  # heap: (arrival, seq, scan, j, payload)
    sent_for = np.zeros(N + 1, dtype=np.int64)  # messages sent for each scan
    on_time_for = np.zeros(N + 1, dtype=np.int64)
    rows = RunRows(N, Ns)

    def send(j: int, scan: int, at: float) -> None:
        """Sensor ``j`` measures scan ``scan`` at time ``at`` and sends it up its link."""
        z = measure(model, j, scan, truth[scan - 1])
        payload = sensors[j].message(rule, model, j, scan, z)
        counts.measured += 1
        sent_for[scan] += 1
        a = up[j].on_send(at)
        if a is None:
            counts.lost += 1
        else:
            heapq.heappush(pending, (a, next(seq), scan, j, payload))

    pred = predict_step(model, est)
    for i in range(N):
        k = i + 1
        t_k = k * T
        t0 = time.perf_counter()
        if rule.information_form:
            alloc = decide(alloc_model, pred.P, k, metric)
        else:
            P_loc = mirror.predicted(model)[1]
            alloc = decide_rule(rule, model, pred.P, P_loc, k, metric, delivery=p_deliver)
        dt = time.perf_counter() - t0
        counts.commanded += len(alloc.subset)
        for j in range(Ns):  # Command(k) goes out on every downlink at t_k
            a = down[j].on_send(t_k)
            if a is not None:
                heapq.heappush(commands, (a, next(seq), j, k, j in alloc.subset))
        d_k = t_k + delta * T
        # the sensors act on the commands that reach them by d_k, in time order
        while commands and commands[0][0] <= d_k:
            a, _, j, scan, on = heapq.heappop(commands)
            sn = sensors[j]
            if scan <= sn.newest:
                continue  # overtaken by a newer command: stale
            for m in range(sn.newest + 1, scan):  # commands it never got: its fallback
                counts.commands_missed += 1
                if {"keep_last": sn.last_on, "off": False, "on": True}[lat.missed_command]:
                    counts.unsolicited += 1
                    send(j, m, a)
            sn.newest, sn.last_on = scan, on
            if on:
                send(j, scan, a)
        # at d_k: late arrivals first (scans < k, in arrival order), then scan k's on-time ones
        on_time: list[tuple[int, Any]] = []
        late: list[tuple[int, int, Any]] = []
        while pending and pending[0][0] <= d_k:
            _, _, scan, j, payload = heapq.heappop(pending)
            (on_time.append((j, payload)) if scan == k else late.append((scan, j, payload)))
        for scan, j, payload in late:
            if not rule.refilters_late or lat.late == "drop":
                counts.late_dropped += 1
            elif buffer.insert(scan, j, *_as_measurement(rule, payload)) is None:
                counts.late_dropped += 1  # older than the buffer
            else:
                counts.late_refiltered += 1
        if late and rule.refilters_late:
            pred = buffer.predicted()  # scan k's prior, after re-filtering
        counts.on_time += len(on_time)
        on_time_for[k] = len(on_time)
        counts.per_scan_fused.append(len(on_time))
        on_time.sort(key=lambda m: m[0])
        if rule.refilters_late:  # every scan through the buffer, so late ones can be re-filtered
            meas = [(j, *_as_measurement(rule, payload)) for j, payload in on_time]
            est = buffer.step(k, meas, prior=pred).post
        else:
            est = rule.fuse(model, pred, on_time)
            mirror.advance(rule, model, [j for j, _ in on_time])
            for j, tr in on_time:
                mirror.P_local[j] = tr.post.P
        rows.put(
            i,
            alloc.subset,
            alloc.value,
            pred,
            est,
            truth[i],
            dt,
            alloc.n_evaluated,
            lower_bound=alloc.lower_bound,
            gap=alloc.gap,
        )
        pred = predict_step(model, est)
    counts.lost += len(pending)  # still in flight at the end: never arrived (as in covnet up)
    counts.deadline_misses = int(np.sum(sent_for > on_time_for))
    return rows.run(metric), counts


class _Sensor:
    """A sensor's state in the simulation: its newest command and, in the decentralized modes,
    its own filter (predicting lazily up to the scan it measures, as the process does)."""

    def __init__(self, model: Model, initial: str) -> None:
        self.local = initial_estimate(model, initial)
        self.scan = self.newest = 0
        self.last_on = False

    def message(self, rule: FusionRule, model: Model, j: int, scan: int, z: np.ndarray) -> Any:
        """What sensor ``j`` sends for scan ``scan``, having measured ``z``: the rule's local
        step (a track rule's local filter predicts up to the scan, then updates)."""
        if not rule.tracks:
            return rule.local(model, j, self.local, z)
        g = self.local
        while self.scan < scan:
            g = predict_step(model, g)
            self.scan += 1
        tr = rule.local(model, j, g, z)
        self.local = tr.post
        return tr


def run_targets_latency(
    sc: Scenario, metric: str, tm: Any = None
) -> tuple[TargetsRun, LatencyCounts]:
    """Many targets (a config with ``targets:``) over the slow links of ``network.latency``,
    in simulated time: the protocol of the module docstring, with each command naming every
    enabled sensor's target and clutter window.  A sensor acts on the newest command that
    reaches it (an older one arriving after it is stale) and dwells as commanded; a scan whose
    command never reached it is not measured (``missed_command`` is ``off`` with targets: a
    fallback dwell would have no target and no window).  At ``d_k`` the late returns (or local
    tracks, ``info``) are re-filtered from their scan (``late: oosm``,
    :class:`covnet.covariance_control.targets.History`, up to ``oosm_depth`` scans back) or
    dropped, then scan ``k`` is fused from its (re-filtered) prior with the decision and
    windows made at ``t_k``.  With ideal links it is :func:`covnet.covariance_control.simulate.
    run_targets` bit for bit."""
    # start-up: the many-target steps only for configs with targets
    from covnet.covariance_control import targets

    tm = tm or targets.build(sc)
    lat = sc.network.latency
    T, delta = tm.T, sc.network.deadline_fraction
    N, K, n_targets = len(tm.sensors), tm.scans, len(tm.targets)
    truth = targets.truth_trajectories(tm)
    up_specs, down_specs = link_specs(sc)
    up = [LinkState(s, link_stream(sc.seed, j, UP)) for j, s in enumerate(up_specs)]
    down = [LinkState(s, link_stream(sc.seed, j, DOWN)) for j, s in enumerate(down_specs)]
    info = sc.fusion.mode == "info"
    local = [targets.LocalTargets(tm, j) for j in range(N)] if info else []
    history = targets.History(tm, lat.oosm_depth if lat.late == "oosm" else 1, info)
    counts = LatencyCounts()
    rows = TargetRows(K, N, n_targets)
    est = targets.initial_estimates(tm)
    newest = [0] * N
    seq = itertools.count()
    commands: list[tuple[float, int, int, int]] = []  # heap: (arrival, seq, j, scan)
    pending: list[tuple[float, int, int, int, Any]] = []  # heap: (arrival, seq, scan, j, payload)
    plans: dict[int, tuple[Any, dict[int, Any]]] = {}  # scan -> (decision, windows)
    sent_for = np.zeros(K + 1, dtype=np.int64)
    on_time_for = np.zeros(K + 1, dtype=np.int64)
    preds = targets.predict_all(tm, est)
    for i in range(K):
        k = i + 1
        t_k = k * T
        t0 = time.perf_counter()
        dec = targets.decide(tm, preds, k, metric)
        dt = time.perf_counter() - t0
        windows = {j: targets.window(tm, j, preds[dec.assignment[j]]) for j in dec.subset}
        plans[k] = (dec, windows)
        counts.commanded += len(dec.subset)
        for j in range(N):
            a = down[j].on_send(t_k)
            if a is not None:
                heapq.heappush(commands, (a, next(seq), j, k))
        d_k = t_k + delta * T
        while commands and commands[0][0] <= d_k:
            a, _, j, scan = heapq.heappop(commands)
            if scan <= newest[j]:
                continue  # overtaken by a newer command: stale
            counts.commands_missed += scan - newest[j] - 1
            newest[j] = scan
            dec_s, win_s = plans[scan]
            t = dec_s.assignment[j]
            if t == targets.OFF:
                continue
            Z = targets.dwell(tm, j, scan, truth[t, scan - 1], win_s[j])
            payload: Any = Z
            if info:
                payload = local[j].track(t, scan, Z, win_s[j])[0]
            counts.measured += 1
            sent_for[scan] += 1
            arrival = up[j].on_send(a)
            if arrival is None:
                counts.lost += 1
            else:
                heapq.heappush(pending, (arrival, next(seq), scan, j, payload))
        on_time: dict[int, Any] = {}
        late: list[tuple[int, int, Any]] = []
        while pending and pending[0][0] <= d_k:
            _, _, scan, j, payload = heapq.heappop(pending)
            if scan == k:
                on_time[j] = payload
            else:
                late.append((scan, j, payload))
        for scan, j, payload in late:
            if lat.late == "oosm" and history.insert(scan, j, payload):
                counts.late_refiltered += 1
            else:
                counts.late_dropped += 1
        prior = history.predicted() if history.changed else preds
        counts.on_time += len(on_time)
        on_time_for[k] = len(on_time)
        counts.per_scan_fused.append(len(on_time))
        est, dwells = history.step(k, prior, dec, windows, on_time)
        rows.put(i, dec, prior, est, dwells, truth[:, i], dt)
        preds = targets.predict_all(tm, est)
    counts.lost += len(pending)
    counts.deadline_misses = int(np.sum(sent_for > on_time_for))
    return rows.run(metric), counts
