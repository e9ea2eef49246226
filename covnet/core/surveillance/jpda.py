"""Joint probabilistic data association (JPDA) of one sensor dwell's returns over many tracks.

A dwell gives ``M`` unlabeled returns ``Z`` ``(M, dim_z)``; tracks ``t = 1..T`` each have a
measurement prediction (``ẑ_t, S_t, K_t``; :func:`covnet.core.ekf.predict_measurement`), a
detection probability ``P_D,t`` (``0`` outside coverage) and the common χ² gate (probability
``P_G``, :func:`covnet.core.association.gate`).  Clutter is Poisson with spatial density ``λ``.

**Clusters.**  Track ``t`` gates the rows ``G_t`` (``d²_{t,i} = ν_{t,i}ᵀ S_t⁻¹ ν_{t,i} ≤ γ``).  Two
tracks are linked when their gates share a row; the clusters are the connected components of
that graph (a track whose gate is empty, or whose ``P_D = 0``, is a cluster of its own that
keeps its prior).  Clusters are independent, so the joint events factor over them.

**Joint events** of a cluster with tracks ``𝒯`` and rows ``ℛ = ∪ G_t`` (``m = |ℛ|``): maps
``θ: 𝒯 → {0} ∪ ℛ`` with ``θ(t) ∈ {0} ∪ G_t`` and ``θ(t) = θ(t') ≠ 0 ⇒ t = t'`` (each return
from at most one track, each track at most one return; ``0`` = missed).  With
``g_{t,i} = N(ν_{t,i}; 0, S_t)`` and ``c(θ) = m − #{t: θ(t) ≠ 0}`` the returns left to clutter::

    P(θ | Z) = w(θ) / Σ_θ' w(θ'),
    log w(θ) = Σ_{t: θ(t)=i≠0} [log P_D,t − d²_{t,i}/2 − ½ log det(2π S_t)]
             + Σ_{t: θ(t)=0} log(1 − P_D,t P_G)  +  c(θ) log λ

(Bar-Shalom, Daum & Huang 2009, the parametric JPDAF), normalised in log space (logsumexp).
The factor of an assigned track is ``P_D P_G · g/P_G = P_D g``: the target's return, given it
fell in the gate, has the truncated density ``g / P_G`` -- the same convention as the PDAF of
:mod:`covnet.core.association`, so that a one-track cluster is exactly the PDA
(``β_i : β_0 = P_D g_i : λ (1 − P_D P_G)``, i.e. :func:`~covnet.core.association.pda_weights`).

A factor that is exactly zero (``λ = 0``, or ``P_D P_G = 1`` for a missed track) is taken in
the limit: ``w(θ) = a(θ) ε^{k(θ)}`` with ``k(θ)`` the number of zero factors, ``ε → 0``; only
the events with the smallest ``k`` keep weight.  This is the PDA's convention too (``λ = 0``:
``β_0 = 0`` when something is gated).

**Marginals** per track: ``β_{t,i} = Σ_{θ: θ(t)=i} P(θ)`` and ``β_{t,0} = Σ_{θ: θ(t)=0} P(θ)``
(``β_{t,0} + Σ_i β_{t,i} = 1``).  Each track is then updated with the one PDA combined formula,
:func:`covnet.core.association.pda_combine` (``x⁺ = x⁻ + K ν̄``, ``P⁺ = β_0 P⁻ + (1−β_0) P^c +
K(Σ β_i ν_i ν_iᵀ − ν̄ν̄ᵀ)Kᵀ``).  A one-track cluster uses :func:`pda_weights` itself (bit for bit
:func:`~covnet.core.association.pda_update`); the enumeration gives the same weights to rounding
(a test).

**Exact up to** ``max_events`` (default :data:`MAX_JOINT_EVENTS` = 20 000) feasible joint
events per cluster, counted while they are built (a partial event always extends to at least
one full one, so the count stops as soon as it passes the cap).  **Beyond it, GNN**: the most
probable single joint event, by ``scipy.optimize.linear_sum_assignment`` on the ``T × (m + T)``
cost matrix ``[C | D]``::

    C_{t,i} = −(log P_D,t − d²_{t,i}/2 − ½ log det(2π S_t) − log λ)    (i ∈ G_t, else ∞)
    D_{t,t} = −log(1 − P_D,t P_G)                                       (off-diagonal ∞)

(``−log w(θ)`` up to the constant ``−m log λ``); a zero factor costs ``B`` (``λ = 0``: ``−B`` per
assignment; ``P_D P_G = 1``: ``D_{t,t} = B``) with ``B`` larger than the spread of all finite
costs, the ``ε``-limit above.  Its ``β`` are one-hot (``β_{t,θ(t)} = 1``).  The cluster's
``method`` says which ran (``"pda"`` one track, ``"exact"``, ``"gnn"``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special
from scipy.optimize import linear_sum_assignment

from covnet.core.association import (
    DEFAULT_GATE_PROBABILITY,
    AssociationResult,
    gate,
    pda_combine,
    pda_weights,
)
from covnet.core.ekf import MeasurementPrediction, predict_measurement
from covnet.core.gaussian import Gaussian, Mat, Vec
from covnet.core.sensor_models import SensorModel

__all__ = [
    "MAX_JOINT_EVENTS",
    "JPDACluster",
    "JPDAResult",
    "TrackGate",
    "clusters_of",
    "jpda_marginals",
    "jpda_update",
    "track_gate",
]

IntVec = NDArray[np.intp]

#: the default cap on the joint events enumerated exactly in one cluster
MAX_JOINT_EVENTS = 20_000

_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True, slots=True)
class TrackGate:
    """What the association needs of one track on one dwell: the gated ``rows`` of ``Z``
    (ascending) with their ``nu`` ``(m, dim_z)`` and ``d2``; the innovation covariance ``S`` and
    ``log_norm = ½ log det(2π S)``; ``pd`` its detection probability (``0``: it gates
    nothing)."""

    rows: IntVec
    nu: Mat
    d2: Vec
    S: Mat
    log_norm: float
    pd: float


def track_gate(
    pred: MeasurementPrediction, Z: ArrayLike, pd: float, gate_probability: float
) -> TrackGate:
    """:func:`covnet.core.association.gate` of one track, as a :class:`TrackGate`; ``pd = 0``
    gates nothing (the track cannot be detected)."""
    p = float(pd)
    if not (0.0 <= p <= 1.0):
        raise ValueError(f"pd: expected a probability in [0, 1], got {pd!r}")
    rows, nu, d2 = gate(pred, Z, gate_probability)
    if p == 0.0:
        rows, nu, d2 = rows[:0], nu[:0], d2[:0]
    _, logdet = np.linalg.slogdet(pred.S)
    log_norm = 0.5 * (pred.dim_z * _LOG_2PI + float(logdet))
    return TrackGate(rows, nu, d2, pred.S, log_norm, p)


@dataclass(frozen=True, slots=True)
class JPDACluster:
    """Tracks (indices into the input, ascending) whose gates share returns, the ``rows`` of
    ``Z`` any of them gates (ascending), the number of feasible joint events (``n_events``; ``0``
    when the count passed the cap and GNN ran) and the ``method`` that ran: ``"pda"``,
    ``"exact"`` or ``"gnn"``."""

    tracks: IntVec
    rows: IntVec
    n_events: int
    method: str


@dataclass(frozen=True, slots=True)
class JPDAResult:
    """The dwell's association: one :class:`~covnet.core.association.AssociationResult` per
    track in input order (``beta`` over its ``gated`` rows, ``beta0``), the clusters, and the
    rows of ``Z`` inside at least one track's gate (ascending)."""

    updates: tuple[AssociationResult, ...]
    clusters: tuple[JPDACluster, ...]
    gated_rows: IntVec

    @property
    def exact(self) -> bool:
        """True when no cluster fell back to GNN."""
        return all(c.method != "gnn" for c in self.clusters)

    def ungated_rows(self, n_returns: int) -> IntVec:
        """The rows ``0..n_returns-1`` inside no track's gate (ascending): the candidates to
        start tracks (:func:`covnet.core.surveillance.tracks.initiate`)."""
        keep = np.ones(int(n_returns), dtype=bool)
        keep[self.gated_rows] = False
        return np.flatnonzero(keep).astype(np.intp)


def clusters_of(gates: Sequence[TrackGate]) -> list[tuple[IntVec, IntVec]]:
    """The connected components ``(tracks, rows)`` of the track–return gate graph (module
    docstring), ordered by their smallest track; tracks and rows ascending."""
    n = len(gates)
    parent = list(range(n))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    owner: dict[int, int] = {}
    for t, g in enumerate(gates):
        for r in g.rows.tolist():
            if r in owner:
                ra, rb = find(owner[r]), find(t)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
            else:
                owner[r] = t
    members: dict[int, list[int]] = {}
    for t in range(n):
        members.setdefault(find(t), []).append(t)
    out: list[tuple[IntVec, IntVec]] = []
    for root in sorted(members):
        ts = members[root]
        rows = sorted({r for t in ts for r in gates[t].rows.tolist()})
        out.append((np.array(ts, dtype=np.intp), np.array(rows, dtype=np.intp)))
    return out


def _factor_tables(
    gates: Sequence[TrackGate], tracks: IntVec, rows: IntVec, pg: float
) -> tuple[Mat, NDArray[np.int64]]:
    """Per track of the cluster, the log factor and zero count of each option: columns
    ``0..m-1`` the cluster's rows (``−∞`` if not gated), column ``m`` the miss."""
    m = rows.size
    logf = np.full((tracks.size, m + 1), -math.inf)
    zeros = np.zeros((tracks.size, m + 1), dtype=np.int64)
    for j, t in enumerate(tracks.tolist()):
        g = gates[t]
        cols = np.searchsorted(rows, g.rows)
        logf[j, cols] = math.log(g.pd) - 0.5 * g.d2 - g.log_norm
        miss = 1.0 - g.pd * pg
        if miss > 0.0:
            logf[j, m] = math.log(miss)
        else:
            logf[j, m] = 0.0
            zeros[j, m] = 1
    return logf, zeros


def _enumerate(gates: Sequence[TrackGate], tracks: IntVec, rows: IntVec, cap: int) -> IntVec | None:
    """All feasible joint events ``(E, n_tracks)`` (entry: column of the row, ``m`` = missed),
    or ``None`` as soon as more than ``cap`` exist."""
    m = rows.size
    options = [np.searchsorted(rows, gates[t].rows).tolist() for t in tracks.tolist()]
    events: list[tuple[int, ...]] = [()]
    for opts in options:
        nxt: list[tuple[int, ...]] = []
        for ev in events:
            nxt.append((*ev, m))
            used = set(ev)
            nxt.extend((*ev, c) for c in opts if c not in used)
        if len(nxt) > cap:
            return None
        events = nxt
    return np.array(events, dtype=np.intp).reshape(len(events), tracks.size)


def _exact(
    logf: Mat, zeros: NDArray[np.int64], events: IntVec, m: int, log_lam: float | None
) -> Mat:
    """Marginals ``(n_tracks, m + 1)`` (last column ``β_0``) from the enumerated events."""
    n = events.shape[1]
    idx = np.arange(n)
    logw = logf[idx, events].sum(axis=1)
    k = zeros[idx, events].sum(axis=1)
    n_clutter = m - (events != m).sum(axis=1)
    if log_lam is None:  # λ = 0: every clutter return is a zero factor
        k = k + n_clutter
    else:
        logw = logw + n_clutter * log_lam
    keep = (k == k.min()) & np.isfinite(logw)
    w = np.zeros(logw.size)
    w[keep] = np.exp(logw[keep] - special.logsumexp(logw[keep]))
    beta = np.zeros((n, m + 1))
    for j in range(n):
        np.add.at(beta[j], events[:, j], w)
    return beta


def _gnn(logf: Mat, zeros: NDArray[np.int64], m: int, log_lam: float | None) -> Mat:
    """One-hot marginals of the most probable joint event (module docstring)."""
    n = logf.shape[0]
    C = -logf[:, :m] + (0.0 if log_lam is None else log_lam)
    miss = -logf[:, m]
    B = 1.0 + 2.0 * float(np.abs(C[np.isfinite(C)]).sum() + np.abs(miss).sum())
    if log_lam is None:  # λ = 0: each assignment removes one zero (clutter) factor
        C = C - B
    miss = miss + B * zeros[:, m]
    D = np.full((n, n), math.inf)
    D[np.arange(n), np.arange(n)] = miss
    r, c = linear_sum_assignment(np.concatenate([C, D], axis=1))
    beta = np.zeros((n, m + 1))
    for j, col in zip(r.tolist(), c.tolist(), strict=True):
        beta[j, col if col < m else m] = 1.0
    return beta


def jpda_marginals(
    gates: Sequence[TrackGate],
    clutter_density: float,
    gate_probability: float = DEFAULT_GATE_PROBABILITY,
    max_events: int = MAX_JOINT_EVENTS,
) -> tuple[list[tuple[Vec, float]], tuple[JPDACluster, ...]]:
    """Per track ``(β over its gate's rows, β_0)`` and the clusters (module docstring).

    One-track clusters use :func:`~covnet.core.association.pda_weights`; larger ones the exact
    enumeration while it has at most ``max_events`` events, else GNN.
    """
    lam = float(clutter_density)
    if not (math.isfinite(lam) and lam >= 0.0):
        raise ValueError(f"clutter_density: expected a finite number >= 0, got {clutter_density!r}")
    pg = float(gate_probability)
    if not (0.0 < pg <= 1.0):
        raise ValueError(f"gate_probability: expected 0 < P_G <= 1, got {gate_probability!r}")
    if int(max_events) != max_events or max_events < 1:
        raise ValueError(f"max_events: expected an integer >= 1, got {max_events!r}")
    log_lam = math.log(lam) if lam > 0.0 else None
    out: list[tuple[Vec, float]] = [(np.zeros(0), 1.0)] * len(gates)
    clusters: list[JPDACluster] = []
    for tracks, rows in clusters_of(gates):
        if tracks.size == 1:
            g = gates[int(tracks[0])]
            if g.rows.size:
                out[int(tracks[0])] = pda_weights(g.d2, g.S, g.pd, lam, pg)
            clusters.append(JPDACluster(tracks, rows, g.rows.size + 1, "pda"))
            continue
        logf, zeros = _factor_tables(gates, tracks, rows, pg)
        events = _enumerate(gates, tracks, rows, int(max_events))
        m = rows.size
        if events is None:
            B = _gnn(logf, zeros, m, log_lam)
            clusters.append(JPDACluster(tracks, rows, 0, "gnn"))
        else:
            B = _exact(logf, zeros, events, m, log_lam)
            clusters.append(JPDACluster(tracks, rows, int(events.shape[0]), "exact"))
        for j, t in enumerate(tracks.tolist()):
            cols = np.searchsorted(rows, gates[t].rows)
            out[t] = (B[j, cols], float(B[j, m]))
    return out, tuple(clusters)


def jpda_update(
    priors: Sequence[Gaussian],
    Z: ArrayLike,
    model: SensorModel,
    clutter_density: float,
    pd: float | Sequence[float] | None = None,
    gate_probability: float = DEFAULT_GATE_PROBABILITY,
    predictions: Sequence[MeasurementPrediction] | None = None,
    max_events: int = MAX_JOINT_EVENTS,
) -> JPDAResult:
    """Update every track (``priors``, predicted to the dwell's time) with one dwell's returns
    ``Z`` ``(M, dim_z)`` of sensor ``model`` by JPDA (module docstring).

    ``pd``: one probability for all tracks, one per track (e.g. ``0`` outside coverage), or
    ``None`` for ``model.pd``.  ``predictions`` (one per track, from
    :func:`~covnet.core.ekf.predict_measurement` on the same prior and model) saves the
    linearisation.  Each track's result is
    :func:`~covnet.core.association.pda_combine` with its marginals; a track with ``P_D = 0``, no
    gated return, or ``β_0 = 1`` with all ``β_i = 0`` keeps its prior (``gated`` empty when
    ``P_D = 0``).
    """
    n = len(priors)
    if predictions is None:
        preds = [predict_measurement(p, model) for p in priors]
    else:
        preds = list(predictions)
        if len(preds) != n:
            raise ValueError(f"predictions: expected {n} (one per track), got {len(preds)}")
    if pd is None:
        pds = [model.pd] * n
    elif isinstance(pd, int | float):
        pds = [float(pd)] * n
    else:
        pds = [float(v) for v in pd]
        if len(pds) != n:
            raise ValueError(f"pd: expected one value or {n} (one per track), got {len(pds)}")
    ZZ = np.asarray(Z, dtype=np.float64)
    if ZZ.size == 0:
        ZZ = np.zeros((0, model.dim_z))
    gates = [track_gate(preds[t], ZZ, pds[t], gate_probability) for t in range(n)]
    weights, clusters = jpda_marginals(gates, clutter_density, gate_probability, max_events)
    updates: list[AssociationResult] = []
    for t in range(n):
        g, pred, (beta, beta0) = gates[t], preds[t], weights[t]
        if beta0 == 1.0 and not np.any(beta):
            res = AssociationResult(
                priors[t], pred.S, np.zeros(pred.dim_z), g.rows, g.d2, beta, 1.0
            )
        else:
            res = pda_combine(priors[t], pred, g.rows, g.nu, g.d2, beta, beta0)
        updates.append(res)
    gated = sorted({r for g in gates for r in g.rows.tolist()})
    return JPDAResult(tuple(updates), clusters, np.array(gated, dtype=np.intp))
