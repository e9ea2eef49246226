"""Slow, lossy links in simulated time (application-level emulation): what ``covnet run``'s
transport over them (:class:`covnet.covariance_control.drive.SlowLinks`) and the fusion
centre's loss-aware decision share.

The network of ``network.latency`` (per sensor an uplink and a downlink
:class:`~covnet.core.delay.LinkSpec`, each drawing from its own stream of the seed) between the
sensors and the fusion centre, with the real-time protocol of ``covnet up --realtime`` (``T`` the
period, ``δ`` the ``network.deadline_fraction``, ``t_k = k T``, ``d_k = t_k + δ T`` the
deadline of scan k)::

    at t_k    the centre decides scan k (from what it had fused by d_{k-1}) and sends
              Command(k) down every link
    on receipt of Command(k) at a sensor (time a):
              older than its newest command: stale, ignored;
              scans it never got a command for (lost or overtaken) are filled by
              ``missed_command``: keep_last (its newest command's on/off), off or on, measured
              now (so late; with targets always off: no target, no clutter window);
              if enabled: it measures scan k (noise stream (j, k)) and sends at a
    at d_k    the centre: (1) late messages that arrived in (d_{k-1}, d_k] (scans < k) go to
              the engine (re-filtered from their scan, ``late: oosm``, exact, up to
              ``oosm_depth`` scans back, or dropped); (2) it fuses scan k's messages that
              arrived by d_k

So a measurement is on time when its command's delay plus its own delay is at most ``δ T``.
A message lost by its link never arrives.  The centre fuses what it received, whoever sent it
(it knows what each sensor did from what arrives: one that measured on its fallback is fused
too).  With ideal links everything arrives on time and the run is the plain one.

``allocation.account_for_loss``: the decision scales sensor ``j``'s information by its
probability ``p_j`` of delivering on time (command and measurement both arrive, within ``δ T``
together; estimated once from ``20 000`` draws of a dedicated stream per link), i.e. it
allocates on the *expected* information ``Σ p_j J_j`` (``ci``: each local track's expected
information ``Y⁻ + p_j (Y⁺ − Y⁻)``); the fusion itself uses what arrives
(:class:`~covnet.covariance_control.centre.CentreFilter`, the same in the manager).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from covnet.core.delay import DOWN, UP, LinkSpec, link_stream
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.model import Model

PROBABILITY_DRAWS = 20_000
_PROB_STREAM_OFFSET = 1_000  # link indices of the delivery-probability estimate's own streams


@dataclass
class LatencyCounts:
    """What the links did in one run (summed over scans)."""

    commanded: int = 0  # sensors enabled by the centre's commands
    commands_missed: int = 0  # (sensor, scan) whose command a later one overtook (filled in)
    measured: int = 0  # measurements (or tracks) sensors sent
    fallback_sent: int = 0  # ... for a scan whose command never reached the sensor
    unsolicited: int = 0  # fused on time from a sensor not enabled for that scan (as network.json)
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
