"""Fusion rules of the decentralized mode: information-matrix fusion and covariance intersection.

In decentralized mode every sensor ``j`` runs its own local Kalman filter (predict every scan,
update only at the scans where it is enabled and measures) and publishes its local track; the
fusion node combines the tracks with a *fusion rule*.  This module is the pure numerical part
(numpy/scipy, no I/O, no random state).

**Information-matrix fusion** (:func:`information_fusion`) removes the information the local
tracks share with the fused prior (their own prediction)::

    Y = P_f⁻⁻¹ + Σ_j [P_j(k|k)⁻¹ − P_j(k|k−1)⁻¹]
    y = P_f⁻⁻¹ x_f⁻ + Σ_j [P_j(k|k)⁻¹ x_j(k|k) − P_j(k|k−1)⁻¹ x_j(k|k−1)]
    P = Y⁻¹,  x = P y

For a linear Kalman filter each bracket is exactly sensor j's measurement information
``(H_jᵀ R_j⁻¹ H_j, H_jᵀ R_j⁻¹ z_j)``, so it reproduces the centralized filter.

**Covariance intersection** (:func:`covariance_intersection`, :func:`ci_weights`,
:func:`ci_candidates`) fuses estimates with unknown cross-correlation, consistently for any
admissible one::

    P(w) = (Σ_i w_i Y_i)⁻¹,   Y_i = P_i⁻¹,   x = P(w) Σ_i w_i Y_i x_i,   w ∈ simplex

with ``w`` minimising ``log det P(w)`` (``"det"``) or ``tr P(w)`` (``"trace"``), or the closed
form ``w_i ∝ 1 / tr P_i`` (``"fast"``, Niehsen's fast CI).

**The optimiser** (:func:`ci_weights`) is an active-set Newton method on the simplex, batched
over problems with masks.  With ``P = P(w)`` and ``C_i = P Y_i``::

    det:    φ = −log det Y(w),  g_i = ∂φ/∂w_i = −tr(P Y_i),       H_il = tr(P Y_i P Y_l)
    trace:  φ = tr P(w),        g_i = −tr(P Y_i P),               H_il = 2 tr(P Y_i P Y_l P)

(from ``∂P/∂w_i = −P Y_i P``; ``H_il`` written as ``Σ_ab C_i[a,b] C_l[b,a]``, resp.
``2 Σ_ab C_i[a,b] (C_l P)[a,b]``).  Each iteration, on the free set F (components with
``w_i > 0``):

1. Newton step ``v`` from the equality-constrained KKT system
   ``[H_FF + δI, 1; 1ᵀ, 0] [v_F; ν] = [−g_F; 0]`` (``δ = 1e-12 max diag H_FF`` keeps it
   solvable for identical or linearly dependent components), ``v = 0`` off F; Newton decrement
   ``λ² = −gᵀv``;
2. ratio test ``α_max = min(1, min_{v_i<0} w_i / −v_i)`` keeps ``w >= 0``;
3. step length: ``α_max`` if it satisfies Armijo ``φ(w + αv) <= φ(w) − 1e-4 α λ²``, else the
   largest of ``α_max 2^-k`` (k = 1..30, all evaluated at once; ``Y(w + αv) = Y(w) + α Y(v)``) that
   does; a component that reaches 0 leaves F;
4. converged on F when ``λ²/2 <= CI_RTOL · s`` (the estimated objective gap: relative in
   ``det P`` (s = 1, φ is a log) or in ``tr P`` (s = tr P)); that last step is still taken.
   Then the KKT check: a component at 0 with ``g_j < μ − CI_KKT_RTOL |μ|``
   (``μ = Σ_i w_i g_i``, the common gradient value of F at the optimum) should be positive and
   re-enters F (the most violating one); with none, the problem is done.

Iteration cap :data:`CI_MAX_ITER`; a problem whose line search finds no decrease stops there.
Start: equal weights over the mask.  Batching: problems are sorted by their number of components
and solved in chunks of ``_CHUNK`` (1024), each problem's components packed to the front, so the
arrays of a chunk are only as wide as its largest problem; converged problems leave the
iteration.  A problem's arithmetic is per-matrix (gufuncs, stacked matmuls) and the chunking a
function of the masks, so the same input gives the same bits.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray

from covnet.core.cholesky import cho_factor, cho_solve
from covnet.core.gaussian import Gaussian, Mat, Vec, symmetrise

__all__ = [
    "CI_KKT_RTOL",
    "CI_MAX_ITER",
    "CI_OBJECTIVES",
    "CI_RTOL",
    "LocalTrack",
    "ci_candidates",
    "ci_weights",
    "covariance_intersection",
    "information_fusion",
]

#: the covariance-intersection weight rules: minimise det P, minimise tr P, closed form
CI_OBJECTIVES = ("det", "trace", "fast")
#: convergence on the free set: estimated relative objective gap λ²/2 below this
CI_RTOL = 1e-13
#: KKT check: a zero-weight component re-enters when its gradient is below μ by this (relative)
CI_KKT_RTOL = 1e-10
#: iteration cap of the Newton method
CI_MAX_ITER = 100

_ARMIJO = 1e-4
_LADDER = 0.5 ** np.arange(1, 31)
_DAMPING = 1e-12
#: problems per chunk of the batched optimiser (bounds the memory of the (m, n, d, d) arrays)
_CHUNK = 1024


# --------------------------------------------------------------------------------------------
# information-matrix fusion
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class LocalTrack:
    """A sensor's local filter output at scan k: posterior and its own prediction for the same
    scan (``post = N(x_j(k|k), P_j(k|k))``, ``prior = N(x_j(k|k−1), P_j(k|k−1))``)."""

    post: Gaussian
    prior: Gaussian

    def __post_init__(self) -> None:
        for name in ("post", "prior"):
            if not isinstance(getattr(self, name), Gaussian):
                raise TypeError(f"LocalTrack.{name} must be a Gaussian")
        if self.post.dim != self.prior.dim:
            raise ValueError(
                f"LocalTrack.post and .prior must have the same dimension, "
                f"got {self.post.dim} and {self.prior.dim}"
            )


def _information(g: Gaussian, name: str) -> tuple[Mat, Vec]:
    """``(P⁻¹, P⁻¹ x)`` of ``g`` by Cholesky solves; a non-SPD ``P`` is a ``ValueError``."""
    try:
        c = cho_factor(g.P)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise ValueError(f"{name}.P must be symmetric positive definite and finite: {exc}") from exc
    return cho_solve(c, np.eye(g.dim)), cho_solve(c, g.x)


def information_fusion(prior: Gaussian, tracks: Sequence[LocalTrack]) -> Gaussian:
    """Information-matrix fusion with the common (prior) information removed::

        Y = inv(P_f⁻) + Σ_j [inv(P_j(k|k)) − inv(P_j(k|k−1))]
        y = inv(P_f⁻) x_f⁻ + Σ_j [inv(P_j(k|k)) x_j(k|k) − inv(P_j(k|k−1)) x_j(k|k−1)]
        P = inv(Y),  x = P y

    For a linear KF the bracket is exactly that sensor's measurement information
    (``Hᵀ R⁻¹ H``, ``Hᵀ R⁻¹ z``), so with every enabled sensor's track arriving every scan this
    equals the centralized filter (a track of a sensor that did not measure adds 0).

    ``prior``: the fused prediction ``N(x_f⁻, P_f⁻)``; ``tracks`` in the caller's canonical order
    (sorted by sensor index), processed in that order.  Every inverse is a Cholesky solve; each
    bracket is formed before it is added (the cancellation stays within one track); ``P`` is
    symmetrised.  Raises ``ValueError`` for a dimension mismatch or a covariance (or the fused
    information) that is not positive definite.
    """
    if not isinstance(prior, Gaussian):
        raise TypeError(f"prior must be a Gaussian, got {type(prior)}")
    n = prior.dim
    Y, y = _information(prior, "prior")
    for j, t in enumerate(tracks):
        if not isinstance(t, LocalTrack):
            raise TypeError(f"tracks[{j}] must be a LocalTrack, got {type(t)}")
        if t.post.dim != n:
            raise ValueError(f"tracks[{j}] has dimension {t.post.dim}, the prior {n}")
        Yp, yp = _information(t.post, f"tracks[{j}].post")
        Ym, ym = _information(t.prior, f"tracks[{j}].prior")
        Y = Y + (Yp - Ym)
        y = y + (yp - ym)
    try:
        cY = cho_factor(symmetrise(Y))
    except np.linalg.LinAlgError as exc:
        raise ValueError(
            "the fused information Y is not positive definite (a track's posterior holds less "
            f"information than its prior?): {exc}"
        ) from exc
    return Gaussian(cho_solve(cY, y), symmetrise(cho_solve(cY, np.eye(n))))


# --------------------------------------------------------------------------------------------
# batched SPD helpers
# --------------------------------------------------------------------------------------------


def _cholesky(A: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Batched lower Cholesky factors of ``A (..., d, d)`` and which ones exist (a failed one is
    returned as the identity, flagged ``False``)."""
    try:
        # float64 in, float64 out (numpy's stubs promise only some floating type)
        return cast(Mat, np.linalg.cholesky(A)), np.ones(A.shape[:-2], dtype=bool)
    except np.linalg.LinAlgError:
        flat = A.reshape(-1, *A.shape[-2:])
        L = np.empty_like(flat)
        ok = np.ones(flat.shape[0], dtype=bool)
        for k in range(flat.shape[0]):
            try:
                L[k] = np.linalg.cholesky(flat[k])
            except np.linalg.LinAlgError:
                L[k] = np.eye(A.shape[-1])
                ok[k] = False
        return L.reshape(A.shape), ok.reshape(A.shape[:-2])


def _spd_inverse(A: NDArray[np.float64]) -> NDArray[np.float64]:
    """``A⁻¹ = L⁻ᵀ L⁻¹`` from the Cholesky factor ``A = L Lᵀ``, symmetrised; batched per matrix
    (a matrix gets the same bits alone or in a stack).  Raises ``LinAlgError`` unless SPD."""
    Li = np.linalg.inv(np.linalg.cholesky(A))
    return symmetrise(np.swapaxes(Li, -1, -2) @ Li)


def _objective(Y: NDArray[np.float64], objective: str) -> NDArray[np.float64]:
    """``φ = −log det Y = log det P`` (det) or ``tr P = ‖L⁻¹‖²_F`` (trace), ``+inf`` where
    ``Y`` is not positive definite."""
    L, ok = _cholesky(Y)
    if objective == "det":
        phi = -2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)
    else:
        Li = np.linalg.inv(L)
        phi = (Li * Li).sum(axis=(-2, -1))
    return np.where(ok, phi, np.inf)


# --------------------------------------------------------------------------------------------
# covariance intersection: validation
# --------------------------------------------------------------------------------------------


def _check_objective(objective: object) -> str:
    if not isinstance(objective, str) or objective not in CI_OBJECTIVES:
        raise ValueError(f"objective must be one of {CI_OBJECTIVES}, got {objective!r}")
    return objective


def _first_bad(A: NDArray[np.float64]) -> int | None:
    """Index of the first matrix of ``A (k, d, d)`` that is not symmetric (to a relative 1e-9)
    and positive definite (Cholesky), else ``None``."""
    asym = np.abs(A - np.swapaxes(A, -1, -2)).max(axis=(-2, -1))
    bad = asym > 1e-9 * np.abs(A).max(axis=(-2, -1))
    bad |= ~_cholesky(symmetrise(A))[1]
    return int(np.argmax(bad)) if bad.any() else None


def _checked_spd_stack(A: NDArray[np.float64], name: str) -> NDArray[np.float64]:
    """``A (k, d, d)`` finite, symmetric and positive definite (:func:`_first_bad`), returned
    symmetrised; otherwise a ``ValueError`` naming ``name[k]``."""
    if not np.isfinite(A).all():
        raise ValueError(f"{name} has non-finite entries")
    k = _first_bad(A)
    if k is not None:
        raise ValueError(f"{name}[{k}] must be a symmetric positive definite covariance")
    return symmetrise(A)


def _checked_mask(
    mask: object, shape: tuple[int, int], name: str, shape_text: str
) -> NDArray[np.bool_]:
    m = np.asarray(mask)
    if m.dtype != np.bool_:
        raise ValueError(f"{name} must be a boolean array {shape_text}, got dtype {m.dtype}")
    if m.shape != shape:
        raise ValueError(f"{name} must be {shape_text} = {shape}, got shape {m.shape}")
    return m


# --------------------------------------------------------------------------------------------
# covariance intersection: the batched optimiser
# --------------------------------------------------------------------------------------------


def ci_weights(
    Y: NDArray[np.float64], mask: NDArray[np.bool_], objective: str = "det"
) -> NDArray[np.float64]:
    """Batched covariance-intersection weights.

    ``Y``: ``(M, n, d, d)`` information matrices (inverse covariances) of up to ``n``
    components per problem; ``mask``: ``(M, n)`` bool, which components take part (at least one
    per row; masked-out entries of ``Y`` are ignored but must be finite).  Returns ``w (M, n)``,
    ``w >= 0``, rows summing to 1, zero where ``mask`` is False::

        P(w) = inv(Σ_i w_i Y_i)
        'det':   argmin_w log det P(w)   (convex; −log det is self-concordant)
        'trace': argmin_w tr P(w)        (convex)
        'fast':  closed form w_i ∝ 1 / tr(P_i) (Niehsen's fast CI), no optimisation

    Method and tolerances: module docstring.  Where the optimum is not unique (identical or
    linearly dependent components) ``P(w)`` still is; the weights are one minimiser.
    """
    objective = _check_objective(objective)
    Y = np.asarray(Y, dtype=np.float64)
    if Y.ndim != 4 or Y.shape[2] != Y.shape[3] or 0 in Y.shape:
        raise ValueError(
            f"Y must be (M, n, d, d) information matrices with M, n, d >= 1, got shape {Y.shape}"
        )
    m = _checked_mask(mask, Y.shape[:2], "mask", "(M, n) like Y")
    empty = ~m.any(axis=1)
    if empty.any():
        raise ValueError(
            f"mask row {int(np.argmax(empty))} has no component: every problem needs at least one"
        )
    if not np.isfinite(Y).all():
        raise ValueError("Y has non-finite entries")
    rows, cols = np.nonzero(m)
    Ys = np.zeros_like(Y)
    k = _first_bad(Y[rows, cols])
    if k is not None:
        raise ValueError(
            f"Y[{rows[k]}, {cols[k]}] must be a symmetric positive definite information matrix"
        )
    Ys[rows, cols] = symmetrise(Y[rows, cols])
    return _weights(Ys, m, objective)


def _weights(
    Y: NDArray[np.float64], mask: NDArray[np.bool_], objective: str
) -> NDArray[np.float64]:
    """:func:`ci_weights` on checked input.  ``Y`` is ``(M, n, d, d)``, or ``(1, n, d, d)``
    shared by every problem (then only the masks differ: :func:`ci_candidates`); masked-out
    entries are zero.  Chunking and packing: module docstring."""
    M, n = mask.shape
    if objective == "fast":
        if Y.shape[0] == 1:
            tr = np.broadcast_to(np.trace(_spd_inverse(Y[0]), 0, -2, -1), mask.shape)
        else:
            tr = np.ones(mask.shape)
            rows, cols = np.nonzero(mask)
            tr[rows, cols] = np.trace(_spd_inverse(Y[rows, cols]), 0, -2, -1)
        inv_tr = np.where(mask, 1.0 / tr, 0.0)
        w_fast: NDArray[np.float64] = inv_tr / inv_tr.sum(axis=1, keepdims=True)
        return w_fast
    # Problems sorted by their number of components and each one's components packed to the
    # front (in index order): a chunk's arrays are only as wide as its largest problem.
    counts = mask.sum(axis=1)
    order = np.argsort(counts, kind="stable")
    packed = np.argsort(~mask, axis=1, kind="stable")
    w = np.zeros((M, n))
    for s in range(0, M, _CHUNK):
        rows = order[s : s + _CHUNK]
        idx = packed[rows, : counts[rows].max()]
        Yc = Y[0][idx] if Y.shape[0] == 1 else Y[rows[:, None], idx]
        w[rows[:, None], idx] = _newton(Yc, np.take_along_axis(mask[rows], idx, axis=1), objective)
    return w


def _newton(Y: NDArray[np.float64], mask: NDArray[np.bool_], objective: str) -> NDArray[np.float64]:
    """The active-set Newton method of the module docstring on one chunk of problems:
    ``Y (m, n, d, d)``, ``mask (m, n)``; returns ``w (m, n)``."""
    m, n = mask.shape
    d = Y.shape[-1]
    Yf = Y.reshape(m, n, d * d)
    w: NDArray[np.float64] = mask / mask.sum(axis=1, keepdims=True)
    free = mask.copy()
    act = np.flatnonzero(mask.sum(axis=1) > 1)  # one component: w = [1], nothing to optimise
    diag = np.arange(n)
    for _ in range(CI_MAX_ITER):
        if act.size == 0:
            break
        a = act.size
        Ya, Yfa = Y[act], Yf[act]
        wa, fa, ma = w[act], free[act], mask[act]
        Yw = (wa[:, None, :] @ Yfa)[:, 0].reshape(a, d, d)
        L = np.linalg.cholesky(Yw)
        Li = np.linalg.inv(L)
        P = symmetrise(np.swapaxes(Li, -1, -2) @ Li)
        C = P[:, None] @ Ya  # C_i = P Y_i, (a, n, d, d)
        if objective == "det":
            phi = -2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)
            g = -np.trace(C, 0, -2, -1)
            B = np.swapaxes(C, -1, -2)  # H_il = Σ_ab C_i[a,b] C_l[b,a]
            scale = np.ones(a)
        else:
            phi = np.trace(P, 0, -2, -1)
            B = C @ P[:, None]  # P Y_l P (symmetric); H_il = 2 Σ_ab C_i[a,b] B_l[a,b]
            g = -np.trace(B, 0, -2, -1)
            B = 2.0 * B
            scale = phi
        H = symmetrise(C.reshape(a, n, d * d) @ B.reshape(a, n, d * d).transpose(0, 2, 1))
        # equality-constrained Newton step on the free set (identity rows off it: v_i = 0)
        both = fa[:, :, None] & fa[:, None, :]
        K = np.zeros((a, n + 1, n + 1))
        K[:, :n, :n] = np.where(both, H, 0.0)
        hd = np.where(fa, H[:, diag, diag], 0.0)
        K[:, diag, diag] = np.where(fa, hd + _DAMPING * hd.max(axis=1, keepdims=True), 1.0)
        K[:, :n, n] = fa
        K[:, n, :n] = fa
        rhs = np.zeros((a, n + 1))
        rhs[:, :n] = np.where(fa, -g, 0.0)
        v = np.where(fa, np.linalg.solve(K, rhs[..., None])[:, :n, 0], 0.0)
        dec = -(g * v).sum(axis=1)  # Newton decrement λ²
        conv = 0.5 * dec <= CI_RTOL * scale
        # ratio test: the largest step keeping w >= 0
        neg = v < 0.0
        ratio = np.where(neg, wa / np.where(neg, -v, 1.0), np.inf)
        amax = np.minimum(1.0, ratio.min(axis=1))
        Yv = (v[:, None, :] @ Yfa)[:, 0].reshape(a, d, d)
        alpha = _step_length(Yw, Yv, phi, dec, amax, conv, objective)
        wn = wa + alpha[:, None] * v
        blocked = neg & (ratio <= amax[:, None]) & (alpha == amax)[:, None]
        drop = fa & (blocked | (wn <= 0.0))
        wn[drop | ~fa] = 0.0
        wn /= wn.sum(axis=1, keepdims=True)
        fn = fa & ~drop
        # KKT check at the current point, for problems converged on their free set
        mu = (wa * g).sum(axis=1)
        viol = ma & ~fn & (g < (mu - CI_KKT_RTOL * np.abs(mu))[:, None])
        release = conv & viol.any(axis=1)
        j = np.argmin(np.where(viol, g, np.inf), axis=1)
        fn[release, j[release]] = True
        w[act], free[act] = wn, fn
        done = (conv & ~release) | (alpha == 0.0)
        act = act[~done]
    return w


def _step_length(
    Yw: NDArray[np.float64],
    Yv: NDArray[np.float64],
    phi: NDArray[np.float64],
    dec: NDArray[np.float64],
    amax: NDArray[np.float64],
    conv: NDArray[np.bool_],
    objective: str,
) -> NDArray[np.float64]:
    """Step length per problem: ``α_max`` when converged (the last, quadratic-region step) or
    when it satisfies Armijo; else the largest ``α_max 2^-k`` that does; 0 when none does."""
    alpha = amax.copy()
    full = _objective(Yw + amax[:, None, None] * Yv, objective)
    bad = ~conv & ~(full <= phi - _ARMIJO * amax * dec)
    if bad.any():
        b = np.flatnonzero(bad)
        steps = amax[b, None] * _LADDER[None, :]
        trial = _objective(Yw[b, None] + steps[..., None, None] * Yv[b, None], objective)
        ok = trial <= (phi[b, None] - _ARMIJO * steps * dec[b, None])
        k = np.argmax(ok, axis=1)
        alpha[b] = np.where(ok.any(axis=1), steps[np.arange(b.size), k], 0.0)
    return alpha


def _fuse(Y: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    """``P = inv(Σ_i w_i Y_i)`` per problem; ``Y (M|1, n, d, d)``, ``w (M, n)``."""
    d = Y.shape[-1]
    Yw = (w[:, None, :] @ Y.reshape(Y.shape[0], Y.shape[1], d * d))[:, 0].reshape(-1, d, d)
    return _spd_inverse(Yw)


def covariance_intersection(tracks: Sequence[Gaussian], objective: str = "det") -> Gaussian:
    """Covariance intersection of ``tracks`` (estimates with unknown cross-correlation)::

        P = inv(Σ_i w_i inv(P_i)),   x = P Σ_i w_i inv(P_i) x_i

    with ``w`` from :func:`ci_weights` (``M = 1``).  Consistent for any admissible
    cross-correlation: ``P ⪰ E[(x − x_true)(x − x_true)ᵀ]`` whenever every ``P_i`` is.
    """
    objective = _check_objective(objective)
    tracks = list(tracks)
    if not tracks:
        raise ValueError("tracks is empty: covariance intersection needs at least one track")
    for i, t in enumerate(tracks):
        if not isinstance(t, Gaussian):
            raise TypeError(f"tracks[{i}] must be a Gaussian, got {type(t)}")
        if t.dim != tracks[0].dim:
            raise ValueError(f"tracks[{i}] has dimension {t.dim}, tracks[0] {tracks[0].dim}")
    Pi = _checked_spd_stack(np.stack([t.P for t in tracks]), "tracks P")
    Y = _spd_inverse(Pi)[None]
    w = _weights(Y, np.ones((1, len(tracks)), dtype=bool), objective)
    P = _fuse(Y, w)[0]
    (nonzero,) = np.nonzero(w[0])
    if nonzero.size == 1 and w[0, nonzero[0]] == 1.0:
        # one track takes all the weight: the mean is that track's.  Through ``P Σ w_i Y_i
        # x_i`` it passed inv(P_i) and its inverse, whose rounding grows with cond(P_i): a
        # sensor of R's least eigenvalue 1e-16 m² put the velocity 30 m/s (120 standard
        # deviations) off, and ci runs diverged (NEES 1 000) where central and info did not
        return Gaussian(tracks[int(nonzero[0])].x.copy(), P)
    y = sum(w[0, i] * (Y[0, i] @ t.x) for i, t in enumerate(tracks))
    return Gaussian(P @ y, P)


def ci_candidates(
    P_prior: Mat, P_local: NDArray[np.float64], masks: NDArray[np.bool_], objective: str = "det"
) -> NDArray[np.float64]:
    """Candidate covariances for the allocator, batched over subsets.

    For each row i of ``masks`` ``(M, Ns)`` bool, the CI covariance of
    ``{P_prior} ∪ {P_local[j] : masks[i, j]}`` (the prior first, then the locals in index
    order); ``P_local (Ns, d, d)`` are the local posteriors each sensor would have if it
    measured.  Returns ``(M, d, d)``; an all-False row gives ``P_prior``.  The same covariance
    (to rounding) as :func:`covariance_intersection` on that set: the components are inverted
    once and shared by every row.
    """
    objective = _check_objective(objective)
    P0 = np.asarray(P_prior, dtype=np.float64)
    if P0.ndim != 2 or P0.shape[0] != P0.shape[1] or P0.shape[0] == 0:
        raise ValueError(f"P_prior must be a square (d, d) covariance, got shape {P0.shape}")
    d = P0.shape[0]
    PL = np.asarray(P_local, dtype=np.float64)
    if PL.ndim != 3 or PL.shape[1:] != (d, d):
        raise ValueError(f"P_local must be (Ns, {d}, {d}) like P_prior, got shape {PL.shape}")
    Ns = PL.shape[0]
    m = np.asarray(masks)
    if m.ndim != 2:
        raise ValueError(f"masks must be (M, Ns) = (M, {Ns}) bool, got shape {m.shape}")
    m = _checked_mask(m, (m.shape[0], Ns), "masks", f"(M, Ns) = (M, {Ns})")
    if not np.isfinite(P0).all() or _first_bad(P0[None]) is not None:
        raise ValueError("P_prior must be a finite symmetric positive definite covariance")
    P0 = symmetrise(P0)
    PL = _checked_spd_stack(PL, "P_local")
    Y = _spd_inverse(np.concatenate([P0[None], PL]))[None]
    full = np.concatenate([np.ones((m.shape[0], 1), dtype=bool), m], axis=1)
    return _fuse(Y, _weights(Y, full, objective))
