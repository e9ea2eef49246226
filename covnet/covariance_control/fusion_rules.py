"""THE fusion-rule registry of the covariance-control kind: ``FUSION_RULES``.

A fusion rule is how a fusion point combines what the sensors send (the spec: "only the
computation of ``P_i`` changes").  Each rule is one class implementing :class:`FusionRule`:

- its **local step** (:meth:`~FusionRule.local`): what an enabled sensor sends for the scan:
  its raw measurement ``(z, R)``, or, when the rule fuses *tracks* (:attr:`~FusionRule.tracks`),
  the local track of its own Kalman filter (predicted every scan, updated when enabled);
- its **centre step** (:meth:`~FusionRule.fuse`): the fusion point's posterior from its
  prediction and what arrived, in ascending sensor index (a canonical order);
- **the covariance the allocator scores** (:meth:`~FusionRule.candidates`): the fused
  covariance of every candidate subset; a rule in the *information form*
  (:attr:`~FusionRule.information_form`: ``P_i = (P⁻⁻¹ + J_i)⁻¹``) is allocated by the exact
  fast search of :mod:`covnet.core.allocation`; any other needs the local filters' covariances
  (the mirror of :mod:`covnet.covariance_control.decentral`);
- its **late-message handling** (:meth:`~FusionRule.late_measurement`): the measurement whose
  information a late message carries, which the out-of-sequence buffer re-filters exactly from
  its scan; ``None`` when the rule has no exact out-of-sequence update (late messages are then
  dropped, and counted).

The rules here: ``central`` (the manager fuses raw measurements by sequential Joseph updates:
the paper's filter), ``info`` (information-matrix fusion of local tracks with each track's own
prior removed: exactly the central filter) and ``ci`` (covariance intersection of the fusion
point's prediction and the local tracks: consistent under any unknown correlation,
conservative).  The maths is in :mod:`covnet.core.fusion` and :mod:`covnet.core.kalman`.

Adding a rule: its maths (``covnet/core/fusion.py``), its class and one ``FUSION_RULES`` line
here; the config accepts its name as ``fusion.mode`` (and, for a track rule, as
``fusion.peer.rule``), ``covnet compare`` offers it, and the in-process runs, the slow-link
simulation, the network processes and the replay use it through this registry.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Protocol

import numpy as np

from covnet.core import registries
from covnet.core.fusion import (
    CI_OBJECTIVES,
    LocalTrack,
    ci_candidates,
    covariance_intersection,
    information_fusion,
)
from covnet.core.gaussian import Gaussian, Mat, Vec, symmetrise
from covnet.core.kalman import update, update_covariance, update_sequential

__all__ = [
    "CI_OBJECTIVES",
    "FUSION_RULES",
    "CovarianceIntersection",
    "Central",
    "FusionRule",
    "InformationFusion",
    "measurement_from_track",
    "PEER",
    "centre_rules",
    "fusion_modes",
    "has_centre",
    "refusal",
    "rule_for",
    "track_rules",
]


class SensorArrays(Protocol):
    """What a rule needs of the model (:class:`covnet.covariance_control.model.Model`)."""

    @property
    def H(self) -> Mat: ...

    @property
    def R(self) -> Mat:
        """``(Ns, 2, 2)``."""
        ...

    @property
    def gains(self) -> Mat:
        """``(Ns, n, n)``: ``J_j = Hᵀ R_j⁻¹ H``."""
        ...


class FusionSettings(Protocol):
    """What a rule needs of the config's ``fusion`` table."""

    @property
    def ci_objective(self) -> str: ...


Payload = Any
"""What a sensor sends under a rule: ``(z, R)`` or a :class:`~covnet.core.fusion.LocalTrack`."""


class FusionRule(Protocol):
    """The protocol every fusion rule implements (module docstring)."""

    name: ClassVar[str]
    tracks: ClassVar[bool]
    """Sensors run local filters and send local tracks (else raw measurements)."""
    information_form: ClassVar[bool]
    """The fused covariance of subset ``D_i`` is ``(P⁻⁻¹ + Σ_{j∈D_i} J_j)⁻¹``."""
    refilters_late: ClassVar[bool]
    """A late message can be re-filtered exactly from its scan (:meth:`late_measurement`)."""
    topologies: ClassVar[frozenset[str]]
    """Where it may fuse: ``centre`` (one fusion point, ``fusion.mode: <name>``), ``peer``
    (every node fuses its neighbours' tracks, ``fusion.mode: peer`` with ``peer.rule``)."""
    many_targets: ClassVar[bool]
    """It runs a ``targets:`` config (each sensor dwells on one target; the many-target
    centre fuses returns by PDA or nearest neighbour, or local tracks by information
    fusion)."""
    refusals: ClassVar[Mapping[str, str]]
    """Why it does not do what it does not (``"targets"``), in the words the config uses when
    it refuses a config asking for it."""

    def __init__(self, settings: FusionSettings) -> None: ...

    def label(self) -> str:
        """The rule in one word, for ``summary.json``'s ``fusion`` (``ci-det``, ...)."""
        ...

    def local(self, model: SensorArrays, j: int, prior: Gaussian, z: Vec) -> Payload:
        """Sensor ``j``'s message at a scan it measured ``z`` (``prior``: its local filter's
        prediction, for a track rule)."""
        ...

    def fuse(
        self, model: SensorArrays, prior: Gaussian, received: Sequence[tuple[int, Payload]]
    ) -> Gaussian:
        """The fusion point's posterior from its prediction and ``(sensor index, payload)``."""
        ...

    def candidates(
        self, model: SensorArrays, P_prior: Mat, P_local_post: Mat, masks: np.ndarray
    ) -> Mat:
        """``(M, n, n)``: the fused covariance when the sensors of each row of ``masks`` report
        (``P_local_post``: each sensor's local posterior covariance if it measures)."""
        ...

    def fused_covariance(
        self, model: SensorArrays, P_prior: Mat, P_local_post: Mat, subset: Sequence[int]
    ) -> Mat:
        """The covariance :meth:`fuse` reaches when ``subset`` reports (it does not depend on
        the measured values): the covariance mirror's update."""
        ...

    def late_measurement(self, payload: Payload) -> tuple[Vec, Mat] | None:
        """The measurement ``(z, R)`` an out-of-sequence update re-filters for a late
        ``payload``; ``None`` for a rule that does not :attr:`refilters_late`."""
        ...


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


def _information_candidates(model: SensorArrays, P_prior: Mat, masks: np.ndarray) -> Mat:
    """The information form ``(P⁻⁻¹ + Σ_j m_ij J_j)⁻¹`` of every row (batched LAPACK)."""
    J = np.einsum("mj,jab->mab", masks.astype(np.float64), model.gains)
    return symmetrise(np.linalg.inv(np.linalg.inv(P_prior) + J))


def _sequential_covariance(model: SensorArrays, P_prior: Mat, subset: Sequence[int]) -> Mat:
    """The covariance of sequential Joseph updates over ``subset`` in ascending index: bit for
    bit what :meth:`Central.fuse` (and :func:`covnet.covariance_control.model.fuse`) give."""
    P = P_prior
    for j in sorted(subset):
        P = update_covariance(P, model.H, model.R[j])
    return P


class Central:
    """``central``: the fusion point takes the raw measurements and updates sequentially
    (Joseph form, ascending sensor index): the paper's centralized filter."""

    name: ClassVar[str] = "central"
    tracks: ClassVar[bool] = False
    information_form: ClassVar[bool] = True
    refilters_late: ClassVar[bool] = True
    topologies: ClassVar[frozenset[str]] = frozenset({"centre"})
    many_targets: ClassVar[bool] = True
    refusals: ClassVar[Mapping[str, str]] = {}

    def __init__(self, settings: FusionSettings) -> None:
        pass

    def label(self) -> str:
        return self.name

    def local(self, model: SensorArrays, j: int, prior: Gaussian, z: Vec) -> Payload:
        return z, model.R[j]

    def fuse(
        self, model: SensorArrays, prior: Gaussian, received: Sequence[tuple[int, Payload]]
    ) -> Gaussian:
        ordered = sorted(received, key=lambda m: m[0])
        return update_sequential(prior, [(z, model.H, R) for _, (z, R) in ordered])

    def candidates(
        self, model: SensorArrays, P_prior: Mat, P_local_post: Mat, masks: np.ndarray
    ) -> Mat:
        return _information_candidates(model, P_prior, masks)

    def fused_covariance(
        self, model: SensorArrays, P_prior: Mat, P_local_post: Mat, subset: Sequence[int]
    ) -> Mat:
        return _sequential_covariance(model, P_prior, subset) if subset else P_prior

    def late_measurement(self, payload: Payload) -> tuple[Vec, Mat] | None:
        z, R = payload
        return z, R


class _TrackRule:
    """What the track rules share: the local step (a local Kalman filter's track), a fusion
    centre or peer nodes; a rule that does not say otherwise has no many-target form."""

    tracks: ClassVar[bool] = True
    topologies: ClassVar[frozenset[str]] = frozenset({"centre", "peer"})
    many_targets: ClassVar[bool] = False
    refusals: ClassVar[Mapping[str, str]] = {
        "targets": "has no many-target form (with 'targets:' use central or info)"
    }

    def __init__(self, settings: FusionSettings) -> None:
        self.settings = settings

    def local(self, model: SensorArrays, j: int, prior: Gaussian, z: Vec) -> Payload:
        """Sensor ``j``'s local Kalman update with its own measurement (Joseph form), as the
        track it publishes (posterior and its own prediction)."""
        return LocalTrack(post=update(prior, z, model.H, model.R[j]), prior=prior)


class InformationFusion(_TrackRule):
    """``info``: information-matrix fusion of the local tracks with each track's own prior
    removed (:func:`covnet.core.fusion.information_fusion`); for linear Kalman filters it is the
    central filter, so the allocator scores the information form, and a late track is
    re-filtered as the measurement whose information it added."""

    name: ClassVar[str] = "info"
    information_form: ClassVar[bool] = True
    refilters_late: ClassVar[bool] = True
    many_targets: ClassVar[bool] = True
    refusals: ClassVar[Mapping[str, str]] = {}

    def label(self) -> str:
        return self.name

    def fuse(
        self, model: SensorArrays, prior: Gaussian, received: Sequence[tuple[int, Payload]]
    ) -> Gaussian:
        ordered = [t for _, t in sorted(received, key=lambda jt: jt[0])]
        return information_fusion(prior, ordered) if ordered else prior

    def candidates(
        self, model: SensorArrays, P_prior: Mat, P_local_post: Mat, masks: np.ndarray
    ) -> Mat:
        return _information_candidates(model, P_prior, masks)

    def fused_covariance(
        self, model: SensorArrays, P_prior: Mat, P_local_post: Mat, subset: Sequence[int]
    ) -> Mat:
        return _sequential_covariance(model, P_prior, subset) if subset else P_prior

    def late_measurement(self, payload: Payload) -> tuple[Vec, Mat] | None:
        return measurement_from_track(payload.post, payload.prior)


class CovarianceIntersection(_TrackRule):
    """``ci``: covariance intersection of the fusion point's prediction and the local tracks'
    posteriors, weights by ``fusion.ci_objective`` (``det``, ``trace`` or the closed form
    ``fast``); consistent under any unknown correlation.  The allocator scores every subset's
    CI covariance from the local filters' covariances; there is no exact out-of-sequence
    update, so late tracks are dropped."""

    name: ClassVar[str] = "ci"
    information_form: ClassVar[bool] = False
    refilters_late: ClassVar[bool] = False
    refusals: ClassVar[Mapping[str, str]] = {
        "targets": "is not available with 'targets:': covariance intersection needs each "
        "sensor's local filter of the target it dwells on and a CI candidate for every "
        "assignment of (T+1)^N, which the many-target allocator does not have (use central "
        "or info)"
    }

    def label(self) -> str:
        return f"ci-{self.settings.ci_objective}"

    def fuse(
        self, model: SensorArrays, prior: Gaussian, received: Sequence[tuple[int, Payload]]
    ) -> Gaussian:
        ordered = [t for _, t in sorted(received, key=lambda jt: jt[0])]
        if not ordered:
            return prior
        return covariance_intersection(
            [prior, *(t.post for t in ordered)], self.settings.ci_objective
        )

    def candidates(
        self, model: SensorArrays, P_prior: Mat, P_local_post: Mat, masks: np.ndarray
    ) -> Mat:
        return ci_candidates(P_prior, P_local_post, masks, self.settings.ci_objective)

    def fused_covariance(
        self, model: SensorArrays, P_prior: Mat, P_local_post: Mat, subset: Sequence[int]
    ) -> Mat:
        if not subset:
            return P_prior
        mask = np.zeros((1, P_local_post.shape[0]), dtype=bool)
        mask[0, list(subset)] = True
        return self.candidates(model, P_prior, P_local_post, mask)[0]

    def late_measurement(self, payload: Payload) -> tuple[Vec, Mat] | None:
        return None


FUSION_RULES: dict[str, type[FusionRule]] = {
    "central": Central,
    "info": InformationFusion,
    "ci": CovarianceIntersection,
}
"""Rule name (``fusion.mode``) -> its class."""
registries.ship("covnet.covariance_control.fusion_rules.FUSION_RULES", FUSION_RULES)


def track_rules() -> tuple[str, ...]:
    """The rules a peer node may use (``fusion.peer.rule``): those whose topologies include
    ``peer`` (they fuse local tracks)."""
    return tuple(name for name, rule in FUSION_RULES.items() if "peer" in rule.topologies)


def centre_rules() -> tuple[str, ...]:
    """The rules a fusion centre may use (``fusion.mode``)."""
    return tuple(name for name, rule in FUSION_RULES.items() if "centre" in rule.topologies)


PEER = "peer"
"""``fusion.mode: peer``: no fusion centre; the topology of peer nodes (``fusion.peer``)."""


def fusion_modes() -> tuple[str, ...]:
    """What ``fusion.mode`` may say: a rule of the registry at a fusion centre, or ``peer``."""
    return (*centre_rules(), PEER)


def refusal(rule: FusionRule, what: str) -> str | None:
    """Why ``rule`` does not do ``what`` (``"targets"``: a many-target config), in its own
    words; None when it does."""
    if what == "targets" and getattr(rule, "many_targets", False):
        return None
    words = getattr(rule, "refusals", {}).get(what)
    return words or f"declares no support for {what!r}"


def has_centre(fusion: Any) -> bool:
    """A config's ``fusion`` table puts a fusion centre in the network (else peer nodes)."""
    return bool(fusion.mode != PEER)


def rule_for(fusion: Any) -> FusionRule:
    """The rule in effect for a config's ``fusion`` table (in peer mode, ``fusion.peer.rule``),
    with its settings."""
    return FUSION_RULES[fusion.peer.rule if fusion.mode == PEER else fusion.mode](fusion)
