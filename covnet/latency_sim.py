"""A scan loop over slow, lossy links, in simulated time (application-level emulation).

The network of ``network.latency`` (per sensor an uplink and a downlink
:class:`~covnet.core.delay.LinkSpec`, each drawing from its own stream of the seed) between the
sensors and a fusion centre, with the real-time protocol (``T`` the period, ``δ`` the
``network.deadline_fraction``, ``t_k = k T``)::

    at d_{k-1} = t_{k-1} + δ T   the centre decides scan k and sends Command(k)   (s_k = d_{k-1})
    at t_k                       sensor j obeys the newest command it has received for a scan
                                 <= k, if that is Command(k); else ``missed_command``:
                                 keep_last (its newest command's on/off), off or on
                                 an obeying sensor measures (noise stream (j, k)) and sends
    at d_k = t_k + δ T           the centre: (1) late measurements that arrived in (d_{k-1}, d_k]
                                 (scans < k): re-filtered from their scan (``late: oosm``, exact,
                                 up to ``oosm_depth`` scans back, older ones dropped) or dropped
                                 (``late: drop``); (2) fuses scan k's measurements that arrived
                                 by d_k; (3) decides scan k+1

A message lost by its link never arrives.  The centre fuses what it received, whoever sent it
(it knows what each sensor did from what arrives: a sensor that measured on a stale command is
fused too).  With ideal links every measurement arrives on time and the loop is exactly the
plain one (:func:`covnet.simulate.run_metric`, the same bits for ``central``).

Fusion modes: ``central`` (measurements); ``info`` (local tracks; a track's new information
``(Y⁺ − Y⁻, y⁺ − y⁻) = (Hᵀ R⁻¹ H, Hᵀ R⁻¹ z)`` is the measurement's, so the centre recovers
``R = (H ΔY Hᵀ)⁻¹``, ``z = R H Δy`` and filters those: late tracks are re-filtered exactly
like late measurements); ``ci`` (covariance intersection has no exact out-of-sequence update:
late tracks are dropped and counted).  Peer mode has no centre and is not simulated here.

``allocation.account_for_loss``: the decision scales sensor ``j``'s information by its
probability ``p_j`` of delivering on time (command in time for ``t_k`` and measurement in time
for ``d_k``; estimated once from ``20 000`` draws of a dedicated stream per link), i.e. it
allocates on the *expected* information ``Σ p_j J_j`` (``ci``: each local track's expected
information ``Y⁻ + p_j (Y⁺ − Y⁻)``); the fusion itself uses what arrives.
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from covnet.config import Scenario
from covnet.core.allocation import prepare
from covnet.core.delay import LinkSpec, LinkState, link_stream
from covnet.core.gaussian import Gaussian
from covnet.core.kalman import nees
from covnet.core.oosm import ReFilterBuffer
from covnet.decentral import Mirror, decide_rule, fuse_tracks, local_track
from covnet.model import (
    Model,
    build_model,
    decide,
    initial_estimate,
    measure,
    predict_step,
    truth_trajectory,
)
from covnet.simulate import MetricRun

UP, DOWN = 0, 1  # link directions (covnet.core.delay.link_stream)
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
        d = {k: v for k, v in self.__dict__.items() if k != "per_scan_fused"}
        return d


def link_specs(sc: Scenario) -> tuple[list[LinkSpec], list[LinkSpec]]:
    """Per sensor (table order) the uplink and downlink specs."""
    lat = sc.network.latency
    return (
        [lat.link(s, "uplink") for s in sc.sensor_ids],
        [lat.link(s, "downlink") for s in sc.sensor_ids],
    )


def _p_within(link: LinkSpec, horizon_s: float, rng: np.random.Generator) -> float:
    """``P(delivered within horizon_s)`` of one message: not lost, delay + jitter <= horizon
    (Monte Carlo over :data:`PROBABILITY_DRAWS` draws)."""
    d = link.delay.sample(rng, PROBABILITY_DRAWS)
    if link.jitter_s > 0:
        d = d + link.jitter_s * rng.standard_normal(PROBABILITY_DRAWS)
    return float((1.0 - link.loss) * np.mean(np.maximum(d, 0.0) <= horizon_s))


def delivery_probabilities(sc: Scenario) -> np.ndarray:
    """``p_j``: command in time for ``t_k`` (within ``(1 − δ) T``) and measurement in time for
    ``d_k`` (within ``δ T``), per sensor (see the module docstring)."""
    T, delta = sc.period_s, sc.network.deadline_fraction
    up, down = link_specs(sc)
    p = []
    for j, (u, dn) in enumerate(zip(up, down, strict=True)):
        i = _PROB_STREAM_OFFSET + j
        p.append(
            _p_within(u, delta * T, link_stream(sc.seed, i, UP))
            * _p_within(dn, (1.0 - delta) * T, link_stream(sc.seed, i, DOWN))
        )
    return np.array(p)


def loss_aware_model(model: Model, p: np.ndarray) -> Model:
    """``model`` whose allocation uses the expected gains ``p_j J_j`` (a sensor that never
    delivers gets a tiny gain, so the plan stays valid)."""
    gains = np.maximum(p, 1e-12)[:, None, None] * model.gains
    return replace(model, gains=gains, plan=prepare(gains, model.constraints), plans={})


def measurement_from_track(post: Gaussian, prior: Gaussian) -> tuple[np.ndarray, np.ndarray]:
    """The position measurement ``(z, R)`` whose information a local track added:
    ``R = (H ΔY Hᵀ)⁻¹``, ``z = R H Δy`` with ``ΔY = P⁺⁻¹ − P⁻⁻¹``, ``Δy = P⁺⁻¹ x⁺ − P⁻⁻¹ x⁻``
    and ``H`` the position selector (rows 0 and 2 of the state)."""
    Yp, Ym = np.linalg.inv(post.P), np.linalg.inv(prior.P)
    dY = Yp - Ym
    dy = Yp @ post.x - Ym @ prior.x
    idx = [0, 2]
    R = np.linalg.inv(dY[np.ix_(idx, idx)])
    R = 0.5 * (R + R.T)
    return R @ dy[idx], R


def _as_measurement(mode: str, payload: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(z, R)`` of a received message: a measurement as is, a local track's information."""
    if mode == "central":
        return payload  # type: ignore[no-any-return]
    return measurement_from_track(payload.post, payload.prior)


def run_latency(
    sc: Scenario, metric: str, model: Model | None = None
) -> tuple[MetricRun, LatencyCounts]:
    """The scan loop of the module docstring for ``sc.fusion.mode`` in central, info or ci."""
    mode = sc.fusion.mode
    if mode == "peer":
        raise ValueError("fusion.mode: peer has no fusion centre; latency runs need one")
    model = model or build_model(sc)
    lat = sc.network.latency
    T, delta = model.T, sc.network.deadline_fraction
    ids = model.sensor_ids
    Ns, N = len(ids), model.scans
    truth = truth_trajectory(model)
    up_specs, down_specs = link_specs(sc)
    up = [LinkState(s, link_stream(sc.seed, j, UP)) for j, s in enumerate(up_specs)]
    down = [LinkState(s, link_stream(sc.seed, j, DOWN)) for j, s in enumerate(down_specs)]
    p_deliver = delivery_probabilities(sc) if sc.allocation.account_for_loss else None
    alloc_model = model
    if p_deliver is not None and mode != "ci":
        alloc_model = loss_aware_model(model, p_deliver)
    counts = LatencyCounts()
    est0 = initial_estimate(model, sc.filter.initial_estimate)
    buffer = ReFilterBuffer(model.F, model.Q, model.H, lat.oosm_depth)
    est = est0
    local = [est0] * Ns  # the sensors' own filters (info, ci)
    mirror = Mirror.start(model)
    # per sensor: commands received, (scan, arrival, enabled)
    inbox: list[list[tuple[int, float, bool]]] = [[] for _ in range(Ns)]
    last_cmd = [False] * Ns  # keep_last: the newest command's on/off for itself
    newest_cmd = [0] * Ns
    pending: dict[float, list[tuple[int, int, Any]]] = defaultdict(list)  # arrival -> messages
    rows = {
        "enabled": np.zeros((N, Ns), dtype=bool),
        "value": np.empty(N),
        "x": np.empty((N, 4)),
        "P": np.empty((N, 4, 4)),
        "Pp": np.empty((N, 4, 4)),
        "nees": np.empty(N),
        "dt": np.empty(N),
        "ne": np.empty(N, dtype=np.int64),
    }
    pred = predict_step(model, est)
    for i in range(N):
        k = i + 1
        t_k = k * T
        s_k = t_k - (1.0 - delta) * T  # the previous deadline
        t0 = time.perf_counter()
        if mode == "ci":
            P_loc = mirror.predicted(model)[1]
            alloc = decide_rule(sc.fusion, model, pred.P, P_loc, k, metric, delivery=p_deliver)
        else:
            alloc = decide(alloc_model, pred.P, k, metric)
        rows["dt"][i] = time.perf_counter() - t0
        counts.commanded += len(alloc.subset)
        # the command goes out on every downlink
        for j in range(Ns):
            a = down[j].on_send(s_k)
            if a is not None:
                inbox[j].append((k, a, j in alloc.subset))
        # at t_k each sensor obeys the newest command it has, or its fallback
        sent: list[int] = []
        for j in range(Ns):
            have = [c for c in inbox[j] if c[1] <= t_k and c[0] <= k]
            inbox[j] = [c for c in inbox[j] if not (c[1] <= t_k and c[0] <= k)]
            for scan, _, on in sorted(have):
                if scan >= newest_cmd[j]:
                    newest_cmd[j], last_cmd[j] = scan, on
            if newest_cmd[j] == k:
                on = last_cmd[j]
            else:
                counts.commands_missed += 1
                on = {"keep_last": last_cmd[j], "off": False, "on": True}[lat.missed_command]
            if on:
                sent.append(j)
        # the obeying sensors measure at t_k and send (local filters: predict, then update)
        local_pred = [predict_step(model, g) for g in local] if mode != "central" else local
        for j in sent:
            z = measure(model, j, k, truth[i])
            counts.measured += 1
            counts.unsolicited += j not in alloc.subset
            if mode == "central":
                payload: Any = (z, model.R[j])
            else:
                payload = local_track(model, j, local_pred[j], z)
                local_pred[j] = payload.post
            a = up[j].on_send(t_k)
            if a is None:
                counts.lost += 1
            else:
                pending[a].append((k, j, payload))
        local = local_pred
        # at d_k: late arrivals first (scans < k, oldest first), then scan k's on-time ones
        d_k = t_k + delta * T
        on_time: list[tuple[int, Any]] = []
        late: list[tuple[int, int, Any]] = []
        for a in sorted(a for a in pending if a <= d_k):
            for scan, j, payload in pending.pop(a):
                (on_time.append((j, payload)) if scan == k else late.append((scan, j, payload)))
        for scan, j, payload in sorted(late, key=lambda m: (m[0], m[1])):
            if mode == "ci" or lat.late == "drop":
                counts.late_dropped += 1
                continue
            z, R = _as_measurement(mode, payload)
            if buffer.insert(scan, j, z, R) is None:
                counts.late_dropped += 1  # older than the buffer
            else:
                counts.late_refiltered += 1
        if late and len(buffer) and mode != "ci":
            pred = buffer.predicted()  # scan k's prior, after re-filtering
        counts.on_time += len(on_time)
        counts.deadline_misses += len(on_time) < len(sent)
        counts.per_scan_fused.append(len(on_time))
        if mode == "ci":
            tracks = sorted(on_time, key=lambda m: m[0])
            est = fuse_tracks(sc.fusion, pred, tracks)
            mirror.advance(sc.fusion, model, [j for j, _ in tracks])
            for j, tr in tracks:
                mirror.P_local[j] = tr.post.P
        else:
            meas = [(j, *_as_measurement(mode, payload)) for j, payload in on_time]
            est = buffer.step(k, meas, prior=pred).post
        rows["enabled"][i, list(alloc.subset)] = True
        rows["value"][i] = alloc.value
        rows["x"][i], rows["P"][i], rows["Pp"][i] = est.x, est.P, pred.P
        rows["nees"][i] = nees(est, truth[i])
        rows["ne"][i] = alloc.n_evaluated
        pred = predict_step(model, est)
    # anything still in flight at the end never made a deadline
    counts.late_dropped += sum(len(v) for v in pending.values())
    run = MetricRun(
        metric,
        rows["enabled"],
        rows["value"],
        rows["x"],
        rows["P"],
        rows["Pp"],
        rows["nees"],
        rows["dt"],
        rows["ne"],
    )
    return run, counts
