"""The fusion centre of a covariance-control network: its filter, in every fusion mode and
over ideal or slow links, and its log.

The manager's loop (:mod:`manager.covariance`) and ``covnet replay``
(:mod:`covnet.covariance_control.replay`) both step :class:`CentreFilter`, so a replay
recomputes exactly what the manager did; both log into :class:`EpisodeLog` and write the run
directory from the same :class:`ManagerResult` (:func:`covnet.covariance_control.results.
write_network_run`).
"""

from __future__ import annotations

import collections
import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import numpy as np

from covnet.core.allocation import Allocation
from covnet.core.fusion import LocalTrack
from covnet.core.gaussian import Gaussian, is_spd
from covnet.core.kalman import gains_sequential
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.decentral import Mirror, decide_rule
from covnet.covariance_control.fusion_rules import FusionRule, rule_for
from covnet.covariance_control.model import Model, decide, usable_measurement
from covnet.covariance_control.runs import MetricRun
from covnet.runs.columns import Column

if TYPE_CHECKING:
    from covnet.core.oosm import ReFilterBuffer
    from covnet.processes.runtime_stats import NetStats
    from covnet.wire import messages as msg

__all__ = [
    "CentreFilter",
    "EpisodeLog",
    "Gains",
    "LateHandler",
    "ManagerResult",
    "as_local_track",
    "fuse_with_gains",
    "position_of",
    "usable_position",
    "usable_track",
]


@dataclass
class EpisodeLog:
    """Rows of one episode, appended per scan; converted to a :class:`MetricRun` at the end.
    Kept in :class:`~covnet.runs.columns.Column` blocks (a long run's memory is its rows' bytes:
    ``covnet bench soak``); ``len(log.value)`` is the number of scans logged."""

    metric: str
    enabled: Column | None = None  # (N,) bool per scan, made at the first row (N known then)
    value: Column = field(default_factory=Column)
    x_est: Column = field(default_factory=lambda: Column((4,)))
    P_post: Column = field(default_factory=lambda: Column((4, 4)))
    P_pred: Column = field(default_factory=lambda: Column((4, 4)))
    nees: Column = field(default_factory=Column)
    decision_s: Column = field(default_factory=Column)
    n_evaluated: Column = field(default_factory=lambda: Column((), np.int64))
    # what a bounded/greedy search reported per scan (NaN where it did not): allocation.search
    lower_bound: Column = field(default_factory=Column)
    gap: Column = field(default_factory=Column)
    reported: set[str] = field(default_factory=set)  # which of the two any scan reported
    failures: list[dict[str, Any]] = field(default_factory=list)

    def record(
        self,
        n_sensors: int,
        alloc: Allocation,
        pred: Gaussian,
        est: Gaussian,
        nees_value: float,
        decision_s: float,
    ) -> None:
        """Append one scan: the allocation, the predicted and fused estimates, NEES, timing."""
        if self.enabled is None:
            self.enabled = Column((n_sensors,), bool)
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
        for name, v in (("lower_bound", alloc.lower_bound), ("gap", alloc.gap)):
            getattr(self, name).append(np.nan if v is None else v)
            if v is not None:
                self.reported.add(name)

    def as_run(self, n_sensors: int) -> MetricRun:
        enabled = (
            self.enabled.array() if self.enabled is not None else np.zeros((0, n_sensors), bool)
        )
        return MetricRun(
            metric=self.metric,
            enabled=enabled,
            value=self.value.array(),
            x_est=self.x_est.array(),
            P_post=self.P_post.array(),
            P_pred=self.P_pred.array(),
            nees=self.nees.array(),
            decision_s=self.decision_s.array(),
            n_evaluated=self.n_evaluated.array(),
            lower_bound=self.lower_bound.array() if "lower_bound" in self.reported else None,
            gap=self.gap.array() if "gap" in self.reported else None,
        )


@dataclass
class ManagerResult:
    """What the loop has done so far (live while it runs; final when :func:`run` returns):
    per metric its episode's log (many targets: a :class:`~covnet.covariance_control.
    targets_centre.TargetEpisodeLog`)."""

    episodes: dict[str, Any]
    stats: NetStats
    completed: bool = False
    error: str | None = None


def payload(rule: FusionRule, m: Any) -> Any:
    """What rule ``rule`` fuses of a received message: a local track, or ``(z, R)``."""
    return as_local_track(m) if rule.tracks else (m.z[0], m.R)


class LateHandler:
    """One episode's out-of-sequence processing on slow links (``network.latency.late``): a
    rule with an exact out-of-sequence update (:meth:`~covnet.covariance_control.fusion_rules.
    FusionRule.late_measurement`: ``central``, ``info``) keeps a
    :class:`~covnet.core.oosm.ReFilterBuffer` of the last ``oosm_depth`` scans and filters every
    scan through it (the same updates as :func:`covnet.covariance_control.model.fuse`; a local
    track enters as the measurement whose information it added), so that a late message is
    re-filtered from its scan; ``ci`` and ``late: drop`` drop late messages.  The loop counts
    which (``late_refiltered`` / ``late_dropped``)."""

    def __init__(self, sc: Scenario, model: Model) -> None:
        lat = sc.network.latency
        self.rule = rule_for(sc.fusion)
        self.ids = model.sensor_ids
        self.inserted = False
        self.refiltered: list[str] = []  # "<sensor>:<scan>" since the last Status
        keep = lat.late == "oosm" and self.rule.refilters_late
        self.buffer: ReFilterBuffer | None = None
        if keep:
            # start-up: the re-filter buffer only for slow links that keep late messages
            from covnet.core.oosm import ReFilterBuffer

            self.buffer = ReFilterBuffer(model.F, model.Q, model.H, lat.oosm_depth)

    def _measurement(self, m: Any) -> tuple[np.ndarray, np.ndarray]:
        zr = self.rule.late_measurement(payload(self.rule, m))
        assert zr is not None
        return zr

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
    covariances of :class:`~covnet.covariance_control.decentral.Mirror`, the only mode that needs
    them); ``insert_late`` takes a late message (slow links: :class:`LateHandler`); ``prior`` is
    scan ``k``'s prior once late messages were re-filtered; ``fuse`` fuses what arrived for scan
    ``k`` (``sensor id -> Measurement | LocalTrack``)."""

    def __init__(self, sc: Scenario, model: Model) -> None:
        self.model = model
        self.rule = rule_for(sc.fusion)
        self.ids = model.sensor_ids
        # only a rule outside the information form decides from the local filters' covariances
        self.mirror = None if self.rule.information_form else Mirror.start(model)
        slow = not sc.network.latency.is_ideal(model.sensor_ids)
        self.late = LateHandler(sc, model) if slow else None
        # allocation.account_for_loss on slow links: decide on the expected information
        self.alloc_model, self.delivery = model, None
        if slow and sc.allocation.account_for_loss:
            # start-up: the link model only for slow links that account for loss
            from covnet.covariance_control.links import delivery_probabilities, loss_aware_model

            p = delivery_probabilities(sc)
            if self.rule.information_form:
                self.alloc_model = loss_aware_model(model, p)
            else:
                self.delivery = p
        self.decisions = DecisionMemo(self.alloc_model)

    def decide(
        self, P_pred: np.ndarray, k: int, metric: str, unavailable: frozenset[int]
    ) -> Allocation:
        if self.mirror is None:
            return self.decisions.decide(P_pred, k, metric, unavailable)
        P_loc = self.mirror.predicted(self.model)[1]
        return decide_rule(
            self.rule, self.model, P_pred, P_loc, k, metric, unavailable, delivery=self.delivery
        )

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
        self, k: int, pred: Gaussian, got: dict[str, Any], gains: Gains | None = None
    ) -> Gaussian:
        """Scan ``k``'s posterior from ``pred`` and what arrived (``gains``: the central
        update's covariance work done ahead, used when it fits)."""
        if self.late is not None and self.late.buffer is not None:
            return self.late.fuse(k, pred, got)
        ids, rule = self.ids, self.rule
        if not rule.tracks and (fast := fuse_with_gains(gains, self.model, pred, got, ids)):
            return fast
        received = [(ids.index(sid), payload(rule, m)) for sid, m in got.items()]
        est = rule.fuse(self.model, pred, received)
        if self.mirror is not None:
            self.mirror.advance(rule, self.model, [j for j, _ in received])
            for j, tr in received:  # what the sensor reports is what it has
                self.mirror.P_local[j] = tr.post.P
        return est


def usable_position(m: msg.Measurement) -> bool:
    """A covariance-control measurement the filter may fuse (see ``usable_measurement``)."""
    return usable_measurement(m.z, m.R)


def usable_track(m: msg.LocalTrack) -> bool:
    """A local track the fusion rules may take: a 4-state estimate with a symmetric positive
    definite posterior and prior covariance."""
    return m.x.shape == (4,) and is_spd(m.P) and is_spd(m.P_prior)


def as_local_track(m: msg.LocalTrack) -> LocalTrack:
    return LocalTrack(post=Gaussian(m.x, m.P), prior=Gaussian(m.x_prior, m.P_prior))


@dataclass(frozen=True)
class Gains:
    """Scan ``k``'s Kalman updates when every enabled sensor's measurement arrives, computed
    while the sensors measure (neither the gains nor the covariances depend on the measured
    values): the gain of each sensor of ``subset`` (ascending index, the order of
    :func:`covnet.covariance_control.model.fuse`) and the posterior covariance, bit for bit those of
    :func:`covnet.covariance_control.model.fused_covariance` and of
    :func:`covnet.covariance_control.model.fuse`."""

    subset: tuple[int, ...]
    R: tuple[bytes, ...]  # each sensor's noise covariance the gains were computed with
    K: tuple[np.ndarray, ...]
    P_post: np.ndarray

    @staticmethod
    def of(model: Model, P_pred: np.ndarray, subset: tuple[int, ...]) -> Gains:
        order = tuple(sorted(subset))
        # = fused_covariance(model, P_pred, [(j, model.R[j]) ...]), step by step
        gains, P = gains_sequential(P_pred, model.H, [model.R[j] for j in order])
        return Gains(order, tuple(model.R[j].tobytes() for j in order), tuple(gains), P)


_K = TypeVar("_K")
_V = TypeVar("_V")


class _Last(Generic[_K, _V]):
    """The last ``size`` values put, by key (the least recently used goes first)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.items: collections.OrderedDict[_K, _V] = collections.OrderedDict()

    def get(self, key: _K) -> _V | None:
        found = self.items.get(key)
        if found is not None:
            self.items.move_to_end(key)
        return found

    def put(self, key: _K, value: _V) -> _V:
        self.items[key] = value
        if len(self.items) > self.size:
            self.items.popitem(last=False)
        return value


def _read_only(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.flags.writeable = False


class GainsMemo:
    """:meth:`Gains.of` for one model, remembering the last :attr:`SIZE` results by the bytes
    of ``P⁻`` and the subset.

    The covariance recursion ``P⁻ -> P⁺ -> P⁻`` does not depend on the measured values, and in
    floating point it reaches a steady state *bit for bit*: with the same subset every scan,
    ``P⁻`` repeats exactly after some scans, on a cycle of a few scans (the bench networks,
    every sensor on: scan 80 -> 81 at 8 sensors, a cycle of 9 scans from scan 86 at 64, of 20
    from scan 88 at 256).  From then on every scan's gains and ``P⁺`` are ones already computed,
    and the same input gives the same bits, so they are returned again instead of computed
    again (256 sequential updates, about 3 ms a scan at 256 sensors).  The arrays returned are
    read-only: shared between scans, they must never be written in place."""

    SIZE = 32

    def __init__(self, model: Model) -> None:
        self.model = model
        self._memo: _Last[tuple[bytes, tuple[int, ...]], Gains] = _Last(self.SIZE)

    def of(self, P_pred: np.ndarray, subset: tuple[int, ...]) -> Gains:
        key = (_bytes(P_pred), tuple(sorted(subset)))
        found = self._memo.get(key)
        if found is not None:
            return found
        gains = Gains.of(self.model, P_pred, subset)
        _read_only(*gains.K, gains.P_post)
        return self._memo.put(key, gains)


class DecisionMemo:
    """:func:`~covnet.covariance_control.model.decide` for one model, remembering the last
    :attr:`SIZE` decisions by the bytes of ``P⁻`` and ``P_d(t_k)``, the metric and the sensors
    unavailable, where a decision is a function of those alone: the covariance-control policy
    (a baseline policy may depend on the scan itself) and no ``allocation.time_limit_s`` (a
    search stopped by the clock may stop elsewhere next time; a node limit is deterministic).
    In a steady state (:class:`GainsMemo`) the next scan's decision is then one already made:
    the same subset, value and certificate, bit for bit.  The decision's ``P`` is read-only."""

    SIZE = 32

    def __init__(self, model: Model) -> None:
        self.model = model
        self.on = model.policy == "covariance_control" and model.search.time_limit_s is None
        self._memo: _Last[tuple[bytes, bytes, str, frozenset[int]], Allocation] = _Last(
            self.SIZE
        )

    def decide(
        self, P_pred: np.ndarray, k: int, metric: str, unavailable: frozenset[int]
    ) -> Allocation:
        if not self.on:
            return decide(self.model, P_pred, k, metric, unavailable)
        key = (_bytes(P_pred), _bytes(self.model.desired(k)), metric, unavailable)
        found = self._memo.get(key)
        if found is not None:
            return found
        alloc = decide(self.model, P_pred, k, metric, unavailable)
        _read_only(alloc.P)
        return self._memo.put(key, alloc)


def _bytes(a: np.ndarray) -> bytes:
    """The float64 bytes of ``a`` (C order): a key equal for equal arrays, bit for bit."""
    return np.ascontiguousarray(a, dtype=np.float64).tobytes()


@functools.lru_cache(maxsize=8)
def _index_of(ids: tuple[str, ...]) -> dict[str, int]:
    """``{sid: ids.index(sid)}`` for the ids of ``ids``."""
    where: dict[str, int] = {}
    for j, sid in enumerate(ids):
        where.setdefault(sid, j)  # the first, as ids.index
    return where


def position_of(ids: tuple[str, ...]) -> Callable[[str], int]:
    """``ids.index`` from a dict (a network's sensors, looked up per message of a scan, where
    ``ids.index`` scans the tuple): the same positions, and the same ``ValueError`` for an id
    not in ``ids``."""
    where = _index_of(ids)
    return lambda sid: where[sid] if sid in where else ids.index(sid)


def fuse_with_gains(
    gains: Gains | None, model: Model, pred: Gaussian, got: dict[str, Any], ids: tuple[str, ...]
) -> Gaussian | None:
    """:func:`covnet.covariance_control.model.fuse` of ``got`` bit for bit, from the gains computed
    ahead, when they are the ones it needs (every enabled sensor's measurement arrived, with the
    noise covariance the gains assumed); None otherwise."""
    if gains is None or len(got) != len(gains.subset):
        return None
    position = position_of(ids)
    ordered = sorted((position(sid), m) for sid, m in got.items())
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
