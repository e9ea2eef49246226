"""THE scan logic of the covariance-control kind: one engine that every driver steps.

Per episode ``e`` (one per allocation metric) and scan ``k = 1..N``, whoever drives it::

    decide   x⁻, P⁻ = predict(x, P) (every target);  the allocation of scan k from P⁻ and
             the sensors that failed (one target: argmin over the feasible subsets of
             f(P_i, P_d(t_k)), P_i the fusion rule's covariance; many targets: the assignment
             of sensors to targets), and what the command says (enabled set, each one's
             target and clutter window)                                        ScanEngine.decide
    ahead    work that does not need the measurements (the Kalman gains, the next decision
             if everything arrives); used only when what arrives is what it assumed  .ahead
    usable   the kind's test of a message's content (the wire checked its form), and of
             the scan's own messages against the prediction (a validation gate: a forged
             or corrupted measurement is never fused)                    .usable, .verdict
    late     a message of an earlier scan (slow links): re-filtered from its scan (OOSM) or
             dropped, as the fusion rule allows                               .insert_late
    fuse     the fusion point's posterior from what arrived                            .fuse
    report   the episode log's row (.record) and the scan's outcome (tracks, status
             numbers: what goes on the bus, what the replay compares)               .report

The drivers, each a loop over these steps and nothing else:

- ``covnet run``: :mod:`covnet.covariance_control.drive` steps it in this process, the
  sensors' responses (:class:`SensorSide`) handed over directly, or over the simulated slow
  links of ``network.latency`` (:mod:`covnet.covariance_control.latency_sim`);
- ``covnet up``: the manager process (:mod:`manager.covariance`) steps it in
  :func:`manager.loop.run_scans` over zenoh;
- ``covnet replay``: :mod:`covnet.covariance_control.replay` steps it with the messages of the
  recording.

So ``run ≡ up ≡ replay`` holds by construction.  What varies between configs (one target or
many, the fusion rule, slow links, the search) is an entry the engine consults: the
``FUSION_RULES`` registry, the targets model, the late handler; never a branch in a driver.

The fusion rule's topology decides what a fusion point is: a **centre** (one fusion point,
:class:`_OneTarget` or :class:`_ManyTargets`) or **peer** nodes (``fusion.mode: peer``,
:class:`_Peers`): no centre; every node decides the same allocation from the covariance mirror
(:class:`covnet.covariance_control.decentral.Mirror`: every node's fused covariance follows from
the enabled history alone), scoring a subset by its worst node, then node ``n`` fuses its own
prediction with the tracks of ``D ∩ ({n} ∪ neighbours(n))``.  In process one engine steps every
node (``covnet run``); each peer process steps an engine of its own node
(``ScanEngine(..., nodes=(n,))``, :mod:`sensors.peer`); the replay one per recorded node.

Messages the engine reads are duck-typed: :class:`covnet.wire.messages.Measurement` and
:class:`~covnet.wire.messages.LocalTrack` over the bus, :class:`Measured` and :class:`Tracked` in
process (the same field names), so ``covnet run`` never imports the wire schemas.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from covnet.core.allocation import Allocation
from covnet.core.gaussian import Gaussian
from covnet.core.kalman import nees
from covnet.core.validation_gate import passes_innovation, passes_track, threshold
from covnet.covariance_control.centre import (
    CentreFilter,
    EpisodeLog,
    Gains,
    GainsMemo,
    ManagerResult,
    as_local_track,
    position_of,
    usable_position,
    usable_track,
)
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.fusion_rules import rule_for
from covnet.covariance_control.model import (
    Model,
    build_model,
    initial_estimate,
    predict_cov,
    predict_step,
    truth_trajectory,
)
from covnet.covariance_control.scan_records import Outcome, Plan
from covnet.covariance_control.sensor_side import Measured, SensorContext, SensorSide, Tracked

if TYPE_CHECKING:
    from covnet.covariance_control.surveillance_episode import SurveillanceEpisode
    from covnet.processes.runtime_stats import NetStats

__all__ = [
    "Measured",
    "Outcome",
    "Plan",
    "ScanEngine",
    "SensorContext",
    "SensorSide",
    "Tracked",
]


# --------------------------------------------------------------------------------------------
# the fusion point of one episode: one target, or many
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Speculation:
    """The allocation of scan ``k``, decided while scan ``k-1``'s measurements were on their
    way, from the covariance the filter reaches if every enabled sensor's measurement arrives.
    It is used only when the real predicted covariance is bit for bit that one and the failed
    set is unchanged, so it never changes a decision, only when it is made."""

    k: int
    P_pred: np.ndarray
    unavailable: frozenset[int]
    alloc: Allocation
    decision_s: float

    def matches(self, k: int, P_pred: np.ndarray, unavailable: frozenset[int]) -> bool:
        return (
            self.k == k and self.unavailable == unavailable and np.array_equal(self.P_pred, P_pred)
        )


class _OneTarget:
    """One episode of the paper's fusion centre: one target, any fusion rule
    (:class:`~covnet.covariance_control.centre.CentreFilter`), ideal or slow links."""

    def __init__(self, sc: Scenario, model: Model, metric: str, truth: np.ndarray) -> None:
        self.sc, self.model, self.metric, self.truth = sc, model, metric, truth
        self.ids = model.sensor_ids
        self.rule = rule_for(sc.fusion)
        self.slow = not sc.network.latency.is_ideal(self.ids)
        self.est = initial_estimate(model, sc.filter.initial_estimate)
        self.centre = CentreFilter(sc, model)
        self.spec: _Speculation | None = None
        self.gains: Gains | None = None
        self.gains_memo = GainsMemo(model)
        self.gate: tuple[Plan, np.ndarray, np.ndarray] | None = None  # the scan's H x⁻, H P⁻ Hᵀ
        self.log = EpisodeLog(metric)

    def decide(self, k: int, unavailable: frozenset[int]) -> Plan:
        pred = predict_step(self.model, self.est)
        spec = self.spec
        if spec is not None and spec.matches(k, pred.P, unavailable):
            alloc, decision_s = spec.alloc, spec.decision_s  # decided ahead, exactly
        else:
            t0 = time.perf_counter()
            alloc = self.centre.decide(pred.P, k, self.metric, unavailable)
            decision_s = time.perf_counter() - t0
        subset = alloc.subset
        enabled = tuple(self.ids[j] for j in subset)
        return Plan(k, subset, enabled, alloc.value, decision_s, (pred, alloc, unavailable))

    def ahead(self, plan: Plan) -> None:
        """The Kalman gains of every enabled sensor's update and the next scan's decision from
        the covariance they give (ideal links, a rule that fuses measurements)."""
        self.gains = None
        if self.rule.tracks or self.slow:
            return
        pred, alloc, unavailable = plan.detail
        self.gains = self.gains_memo.of(pred.P, alloc.subset)
        k_next = plan.k + 1
        self.spec = None
        if k_next <= self.model.scans:
            t0 = time.perf_counter()
            P_next = predict_cov(self.model, self.gains.P_post)
            # the decision decide() would make (the centre's, remembered in a steady state)
            nxt = self.centre.decide(P_next, k_next, self.metric, unavailable)
            self.spec = _Speculation(k_next, P_next, unavailable, nxt, time.perf_counter() - t0)

    def verdict(self, m: Any, plan: Plan | None) -> str | None:
        """None when ``m`` may be fused; else why not: ``bad_measurement`` (its content), or
        ``outside_gate`` (a message of the planned scan impossible under the prediction:
        :mod:`covnet.core.validation_gate`)."""
        if not (usable_track(m) if self.rule.tracks else usable_position(m)):
            return "bad_measurement"
        if plan is None or m.scan != plan.k:
            return None  # a late one: its content only
        pred = plan.detail[0]
        if self.rule.tracks:
            ok = passes_track(m.x, m.P, pred.x, pred.P)
        else:
            _, Hx, HPH = self._gate(plan)
            ok = passes_innovation(m.z[0] - Hx, HPH + m.R)
        return None if ok else "outside_gate"

    def _gate(self, plan: Plan) -> tuple[Plan, Any, Any]:
        """``(plan, H x⁻, H P⁻ Hᵀ)`` of the planned scan's prediction, once per scan."""
        gate = self.gate
        if gate is None or gate[0] is not plan:
            pred, H = plan.detail[0], self.model.H
            gate = self.gate = (plan, H @ pred.x, H @ pred.P @ H.T)
        return gate

    def verdicts(self, ms: Sequence[Any], plan: Plan | None) -> list[str | None]:
        """``[self.verdict(m, plan) for m in ms]``, the same verdicts, with the content test and
        the gate of the planned scan's position measurements computed together (numpy over
        the messages).  Bit for bit :func:`~covnet.covariance_control.model.
        usable_measurement` and :func:`~covnet.core.validation_gate.passes_innovation`: the
        same IEEE operations in the same order, elementwise (``R₀₁²`` as the scalar path
        computes it, a numpy scalar's power), for each message::

            usable = R₀₁ = R₁₀  and  R₀₀ > 0  and  R₀₀ R₁₁ − R₀₁² > 0
            ν = z − H x⁻,  S = H P⁻ Hᵀ + R,  det = s₁₁ s₂₂ − s₁₂ s₁₂,
            pass = (s₂₂ ν₁ ν₁ − 2 s₁₂ ν₁ ν₂ + s₁₁ ν₂ ν₂) / det ≤ γ     (det > 0)

        A message of another scan or shape, a rule that fuses tracks, and a ``det`` that is
        not > 0 (the closed form's own fallback) take :meth:`verdict` itself."""
        out: list[str | None] = [None] * len(ms)
        if self.rule.tracks or plan is None:
            return [self.verdict(m, plan) for m in ms]
        rows = []
        for i, m in enumerate(ms):
            if m.scan == plan.k and m.z.shape == (1, 2) and m.R.shape == (2, 2):
                rows.append(i)
            else:
                out[i] = self.verdict(m, plan)
        if not rows:
            return out
        Z = np.concatenate([ms[i].z for i in rows])
        R = np.concatenate([ms[i].R for i in rows]).reshape(len(rows), 2, 2)
        r01 = R[:, 0, 1]
        sq = np.array([x**2 for x in r01])  # numpy scalars: usable_measurement's R[0, 1] ** 2
        usable = (r01 == R[:, 1, 0]) & (R[:, 0, 0] > 0) & (R[:, 0, 0] * R[:, 1, 1] - sq > 0)
        _, Hx, HPH = self._gate(plan)
        nu = Z - Hx
        S = HPH + R
        a, b, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
        n1, n2 = nu[:, 0], nu[:, 1]
        with np.errstate(all="ignore"):  # det <= 0: the per-message path below
            det = a * d - b * b
            inside = (d * n1 * n1 - 2.0 * b * n1 * n2 + a * n2 * n2) / det <= threshold(2)
        closed = det > 0.0
        for n, i in enumerate(rows):
            if not usable[n]:
                out[i] = "bad_measurement"
            elif not closed[n]:
                out[i] = self.verdict(ms[i], plan)
            elif not inside[n]:
                out[i] = "outside_gate"
        return out

    def insert_late(self, m: Any) -> bool:
        return self.centre.insert_late(m)

    def fuse(self, plan: Plan, got: dict[str, Any]) -> Any:
        pred = self.centre.prior(plan.detail[0])  # re-filtered late messages change the prior
        gains, self.gains = self.gains, None
        self.est = self.centre.fuse(plan.k, pred, got, gains)
        late = self.centre.late
        refiltered = late.take_refiltered() if late is not None else None
        return pred, self.est, refiltered

    def record(self, plan: Plan, fused: Any, got: dict[str, Any]) -> None:
        pred, est, _ = fused
        alloc, k = plan.detail[1], plan.k
        self.log.record(
            len(self.ids), alloc, pred, est, nees(est, self.truth[k - 1]), plan.decision_s
        )

    def outcome(self, plan: Plan, fused: Any, got: dict[str, Any]) -> Outcome:
        _, est, refiltered = fused
        alloc, k = plan.detail[1], plan.k
        return Outcome(
            k,
            ((None, est),),
            plan.enabled,
            float(alloc.value),
            float(np.trace(est.P)),
            float(np.trace(self.model.desired(k))),
            tuple(sorted(got, key=position_of(self.ids))),
            refiltered,
            alloc.lower_bound,
            alloc.gap,
        )


class _ManyTargets:
    """One episode of the many-target centre (:class:`~covnet.covariance_control.
    targets_centre.TargetsCentre`): each sensor dwells on one target or is off."""

    def __init__(self, sc: Scenario, tm: Any, metric: str, truth: np.ndarray) -> None:
        # start-up: the many-target steps only for configs with targets
        from covnet.covariance_control import targets
        from covnet.covariance_control.targets_centre import TargetEpisodeLog, TargetsCentre

        self.tm, self.metric = tm, metric
        self.ids = tm.sensor_ids
        self.tracks = rule_for(sc.fusion).tracks
        lat = sc.network.latency
        history = None
        if not lat.is_ideal(self.ids) and lat.late == "oosm":
            history = targets.History(tm, lat.oosm_depth, self.tracks)
        self.centre = TargetsCentre(tm, history, tracks=self.tracks)
        self.log = TargetEpisodeLog.start(metric, tm, truth)

    def decide(self, k: int, unavailable: frozenset[int]) -> Plan:
        sp = self.centre.decide(k, self.metric, unavailable)
        enabled, tasks, windows = self.centre.command_fields(sp)
        dec = sp.decision
        return Plan(k, dec.subset, enabled, dec.value, sp.decision_s, sp, tasks, windows)

    def ahead(self, plan: Plan) -> None:
        pass

    def verdict(self, m: Any, plan: Plan | None) -> str | None:
        """None when ``m`` may be fused; else ``bad_measurement`` (the returns are gated per
        target when they are associated)."""
        if self.tracks:
            ok = self.centre.usable_track(m, None if plan is None else plan.detail)
        else:
            ok = self.centre.usable(m)
        return None if ok else "bad_measurement"

    def insert_late(self, m: Any) -> bool:
        return self.centre.insert_late(m)

    def fuse(self, plan: Plan, got: dict[str, Any]) -> Any:
        prior, posts, dwells = self.centre.fuse(plan.detail, got)
        return prior, posts, dwells, self.centre.take_refiltered()

    def record(self, plan: Plan, fused: Any, got: dict[str, Any]) -> None:
        prior, posts, dwells, _ = fused
        self.log.record(plan.detail, prior, posts, dwells, sorted(got))

    def outcome(self, plan: Plan, fused: Any, got: dict[str, Any]) -> Outcome:
        _, posts, _, refiltered = fused
        sp, tm, ids, k = plan.detail, self.tm, self.ids, plan.k
        return Outcome(
            k,
            tuple(zip(tm.target_ids, posts, strict=True)),
            plan.enabled,
            float(sp.decision.value),
            float(sum(np.trace(g.P) for g in posts)),
            float(sum(np.trace(tg.desired(k)) for tg in tm.targets)),
            tuple(sorted(got, key=ids.index)),
            refiltered,
            sp.decision.lower_bound,
            sp.decision.gap,
            per_target=tuple(
                (tid, len(sp.decision.on_target(i))) for i, tid in enumerate(tm.target_ids)
            ),
        )


class _Peers:
    """One episode of peer mode (module docstring) for the nodes ``nodes`` (sensor indices:
    every node in process, one in a peer process): the decision from the covariance mirror, the
    failed nodes infeasible and left out of the score; per node its fused estimate and log."""

    def __init__(
        self, sc: Scenario, model: Model, metric: str, truth: np.ndarray, nodes: Sequence[int]
    ) -> None:
        # start-up: the mirror and the peer graph only in peer mode
        from covnet.covariance_control.decentral import (
            Mirror,
            decide_rule,
            neighbours,
            reach_matrix,
        )

        self.decide_rule = decide_rule
        self.model, self.metric, self.truth = model, metric, truth
        self.ids = model.sensor_ids
        self.rule = rule_for(sc.fusion)
        self.reach = reach_matrix(sc.fusion, self.ids)
        self.nbrs = neighbours(sc.fusion, self.ids)
        self.mirror = Mirror.start(model, self.reach)
        self.nodes = tuple(nodes)
        est0 = initial_estimate(model, sc.filter.initial_estimate)
        self.fused = dict.fromkeys(self.nodes, est0)
        self.logs = {n: EpisodeLog(metric) for n in self.nodes}
        self.log = self.logs[self.nodes[0]]

    def decide(self, k: int, unavailable: frozenset[int]) -> Plan:
        """``D = argmin_i max_{n live} f(P_in, P_d(t_k))`` over the feasible subsets, ``P_in``
        node n's fused covariance from the tracks of ``D_i ∩ reach_n``
        (:func:`~covnet.covariance_control.decentral.decide_rule`)."""
        live = np.array([j not in unavailable for j in range(len(self.ids))])
        P_nodes, P_loc = self.mirror.predicted(self.model)
        t0 = time.perf_counter()
        alloc = self.decide_rule(
            self.rule,
            self.model,
            P_nodes[live],
            P_loc,
            k,
            self.metric,
            unavailable,
            reach=self.reach[live],
        )
        decision_s = time.perf_counter() - t0
        enabled = tuple(self.ids[j] for j in alloc.subset)
        return Plan(k, alloc.subset, enabled, alloc.value, decision_s, (alloc, unavailable))

    def ahead(self, plan: Plan) -> None:
        pass

    def verdict(self, m: Any, plan: Plan | None) -> str | None:
        """None when a local track may be fused; else ``bad_measurement`` (its content) or,
        for an engine of one node (a peer process, a node's replay) and a track of the
        planned scan, ``outside_gate``: impossible under that node's prediction
        (:func:`~covnet.core.validation_gate.passes_track`, the test :meth:`fuse` applies per
        node, so an engine of every node, in process, fuses the same tracks)."""
        if not usable_track(m):
            return "bad_measurement"
        if plan is None or m.scan != plan.k or len(self.nodes) != 1:
            return None
        pred = predict_step(self.model, self.fused[self.nodes[0]])
        return None if passes_track(m.x, m.P, pred.x, pred.P) else "outside_gate"

    def insert_late(self, m: Any) -> bool:
        return False  # a peer node fuses a scan's tracks once

    def fuse(self, plan: Plan, got: dict[str, Any]) -> Any:
        """Every node's ``x_n = rule(x_n⁻, tracks of got ∩ ({n} ∪ neighbours(n)))``, each track
        through node ``n``'s validation gate against ``x_n⁻`` (a forged or corrupted track is
        not fused: :func:`~covnet.core.validation_gate.passes_track`, failed by a genuine one
        about once in 10⁹); the mirror then advances with the *decided* subset (what every
        node knows)."""
        heard_all = {self.ids.index(sid): as_local_track(m) for sid, m in got.items()}
        out: dict[int, tuple[Gaussian, Gaussian, tuple[int, ...]]] = {}
        for n in self.nodes:
            pred = predict_step(self.model, self.fused[n])
            heard = [
                (j, heard_all[j])
                for j in (n, *self.nbrs[n])
                if j in heard_all
                and passes_track(heard_all[j].post.x, heard_all[j].post.P, pred.x, pred.P)
            ]
            self.fused[n] = self.rule.fuse(self.model, pred, heard)
            out[n] = (pred, self.fused[n], tuple(j for j, _ in heard))
        self.mirror.advance(self.rule, self.model, plan.subset)
        return out

    def record(self, plan: Plan, fused: Any, got: dict[str, Any]) -> None:
        alloc, k = plan.detail[0], plan.k
        for n, (pred, est, _) in fused.items():
            self.logs[n].record(
                len(self.ids), alloc, pred, est, nees(est, self.truth[k - 1]), plan.decision_s
            )

    def outcome(self, plan: Plan, fused: Any, got: dict[str, Any]) -> Outcome:
        """The first node's outcome (a peer process's own)."""
        _, est, heard = fused[self.nodes[0]]
        k = plan.k
        return Outcome(
            k,
            ((None, est),),
            plan.enabled,
            float(plan.value),
            float(np.trace(est.P)),
            float(np.trace(self.model.desired(k))),
            tuple(self.ids[j] for j in heard),
            None,
        )


# --------------------------------------------------------------------------------------------
# the engine
# --------------------------------------------------------------------------------------------


class ScanEngine:
    """The scan logic of a covariance-control config (module docstring): every episode
    (``metrics``, default ``allocation.metrics``) of one target or many, under the config's
    fusion rule and links.  ``result`` holds each episode's log (a
    :class:`~covnet.covariance_control.centre.ManagerResult`; ``stats`` is the driver's
    counts, empty in process)."""

    def __init__(
        self,
        sc: Scenario,
        metrics: Sequence[str] | None = None,
        *,
        model: Any = None,
        stats: NetStats | None = None,
        many: bool | None = None,
        nodes: Sequence[int] | None = None,
    ) -> None:
        self.sc = sc
        self.episodes = list(sc.allocation.metrics if metrics is None else metrics)
        # the many-target centre (a config with targets:, or any config through its steps)
        self.many = sc.multitarget if many is None else many
        # targets that appear and leave, the manager's own tracks and the search
        self.surveil = sc.surveillance is not None
        if self.surveil:
            # start-up: the surveillance world only for configs with surveillance
            from covnet.covariance_control import surveillance

            sm = model if model is not None else surveillance.build(sc)
            self.model: Any = sm
            self.truth = sm.truth
            self.scans, self.period_s = sm.scans, sm.T
        elif self.many:
            from covnet.covariance_control import targets  # start-up: configs with targets

            tm = model if model is not None else targets.build(sc)
            self.model = tm
            self.truth = targets.truth_trajectories(tm)
            self.scans, self.period_s = tm.scans, tm.T
        else:
            self.model = model if model is not None else build_model(sc)
            self.truth = truth_trajectory(self.model)
            self.scans, self.period_s = self.model.scans, self.model.T
        self.ids: tuple[str, ...] = self.model.sensor_ids
        self.rule = rule_for(sc.fusion)
        # peer mode: the nodes this engine fuses for (every node unless said)
        self.peer = not sc.fusion.has_centre
        self.nodes = tuple(range(len(self.ids)) if nodes is None else nodes)
        self.tracks = self.rule.tracks  # sensors send local tracks, not measurements
        # slow links (network.latency): late messages are re-filtered (or dropped); one
        # target: a sensor that measured on its missed-command fallback is fused too
        self.slow = not sc.network.latency.is_ideal(self.ids)
        self.accept_unsolicited = self.slow and not self.many
        if stats is None:
            # start-up: the network's counters only where a driver has none of its own
            from covnet.processes.runtime_stats import NetStats

            stats = NetStats()
        self.result = ManagerResult({}, stats)
        self.episode: _OneTarget | _ManyTargets | _Peers | SurveillanceEpisode | None = None
        self.plan: Plan | None = None

    def start_episode(self, e: int) -> None:
        metric = self.episodes[e]
        if self.surveil:
            # start-up: the surveillance centre only for configs with surveillance
            from covnet.covariance_control.surveillance_episode import SurveillanceEpisode

            self.episode = SurveillanceEpisode(self.model, metric)
        elif self.peer:
            self.episode = _Peers(self.sc, self.model, metric, self.truth, self.nodes)
        elif self.many:
            self.episode = _ManyTargets(self.sc, self.model, metric, self.truth)
        else:
            self.episode = _OneTarget(self.sc, self.model, metric, self.truth)
        self.result.episodes[metric] = self.episode.log
        self.plan = None

    def _current(self) -> _OneTarget | _ManyTargets | _Peers | SurveillanceEpisode:
        if self.episode is None:
            raise RuntimeError("start_episode first")
        return self.episode

    def failures(self, events: list[dict[str, Any]]) -> None:
        """Failures and rejoins seen at the current scan, for the episode's log."""
        self._current().log.failures.extend(events)

    def decide(self, k: int, unavailable: frozenset[int] = frozenset()) -> Plan:
        """Scan ``k``'s plan; ``unavailable``: the sensors (indices) that failed."""
        self.plan = self._current().decide(k, unavailable)
        return self.plan

    def unavailable(self, failed: frozenset[str]) -> frozenset[int]:
        """The indices of the failed sensors (node ids that are not sensors left out)."""
        return frozenset(self.ids.index(s) for s in failed if s in self.ids)

    def ahead(self, plan: Plan) -> None:
        self._current().ahead(plan)

    def verdict(self, m: Any) -> str | None:
        """Why a sensor's message (of the current scan, or a late one) may not be fused, as a
        rejection reason (``bad_measurement``, ``outside_gate``); None when it may."""
        return self._current().verdict(m, self.plan)

    def verdicts(self, ms: Sequence[Any]) -> list[str | None]:
        """:meth:`verdict` of each message of ``ms`` (the same verdicts; one target's are
        computed together, :meth:`_OneTarget.verdicts`)."""
        ep = self._current()
        many = getattr(ep, "verdicts", None)  # optional: an episode's batch verdicts
        if many is None:
            return [ep.verdict(m, self.plan) for m in ms]
        return many(ms, self.plan)

    def usable(self, m: Any) -> bool:
        """A sensor's message may be fused (:meth:`verdict`)."""
        return self._current().verdict(m, self.plan) is None

    def insert_late(self, m: Any) -> bool:
        """A late message of an earlier scan of this episode: True when re-filtered."""
        return self.slow and self._current().insert_late(m)

    def fuse(self, plan: Plan, got: dict[str, Any]) -> Any:
        """Fuse what arrived for ``plan``'s scan (``sensor id -> message``)."""
        return self._current().fuse(plan, got)

    def record(self, plan: Plan, fused: Any, got: dict[str, Any]) -> None:
        """Log the scan in the episode's log."""
        self._current().record(plan, fused, got)

    def report(self, plan: Plan, fused: Any, got: dict[str, Any]) -> Outcome:
        """Log the scan in the episode's log; its outcome (what the bus and the replay
        compare: tracks, status numbers)."""
        ep = self._current()
        ep.record(plan, fused, got)
        return ep.outcome(plan, fused, got)

    def run_of(self, metric: str) -> Any:
        """Episode ``metric``'s arrays: a :class:`~covnet.covariance_control.simulate.
        MetricRun` (many targets: a :class:`~covnet.covariance_control.simulate.TargetsRun`)."""
        log = self.result.episodes[metric]
        return log.as_run() if self.many or self.surveil else log.as_run(len(self.ids))

    def node_runs(self) -> dict[str, Any]:
        """Peer mode: the current episode's arrays of every node this engine fuses for
        (sensor id -> :class:`~covnet.covariance_control.simulate.MetricRun`)."""
        ep = self._current()
        if not isinstance(ep, _Peers):
            raise ValueError("node_runs: only peer mode has nodes")
        return {self.ids[n]: log.as_run(len(self.ids)) for n, log in ep.logs.items()}
