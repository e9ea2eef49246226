"""The reduced relaxation of a branch-and-bound node (:class:`_Relaxation`; frobenius, kl,
logdet with ``r = 2``), on symmetric ``2 x 2`` matrices held as triples of arrays, and the
LAPACK Cholesky helpers the reduced form shares.

**Relaxation** (frobenius, kl, logdet; ``r = 2``): the Loewner interval ``[A, B]`` has
``n(n+1)/2`` dimensions, the node's completions only the 3 of ``Z ∈ [Z(I), Z(I ∪ U)]``.  For
these metrics, convex in ``Z`` or in ``W = Z⁻¹`` (logdet: on the nodes where it is), a few
projected-gradient steps on that 3-dimensional interval give a tangent-plane lower bound
(:class:`_Relaxation`), applied to every node the interval bound keeps (down to one undecided
sensor: at 32-40 paper-like sensors, refining only nodes with 6 or more undecided left the last
five levels unpruned, most of the tree); on the paper-like problems it removes 95-99 % of the
nodes the interval bound keeps.  What it cannot prune (kl, logdet, frobenius at 32-40 sensors):
nodes whose interval contains the continuous minimiser, whose value is within about ``1e-8`` of
the discrete optimum on those problems, so no continuous bound can separate them; the tree then
enumerates their completions near that point (not ties: one or two subsets within ``tie_rtol``,
but many within ``1e-5``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation.interval_bounds import ROUND, DesiredConstants, IntervalContext
from covnet.core.gaussian import Mat
from covnet.core.lapack import flapack
from covnet.core.metrics import Relaxation

lapack = flapack()  # scipy.linalg.lapack's routines, without scipy.linalg's import

EPS = float(np.finfo(np.float64).eps)
#: the relaxation's relative rounding allowance per unit of ``n² κ``
ROUND_REL = 64.0

#: symmetric 2 x 2 matrices as triples ``(a, b, c)`` of ``(m,)`` arrays: ``[[a, b], [b, c]]``
Sym2 = tuple[Mat, Mat, Mat]

#: projected-gradient iterations of the relaxation per node (each also gives a lower bound)
RELAX_ITERS = 16
#: logdet is convex in ``W`` where every generalized eigenvalue is at most ``1 + sqrt 2``
LOGDET_CONVEX = 1.0 + math.sqrt(2.0)


def _cholesky(A: Mat, name: str) -> Mat:
    """The lower Cholesky factor (LAPACK ``potrf``; the upper triangle is not referenced by
    :func:`_cho_solve`); ``numpy.linalg.LinAlgError`` unless ``A`` is positive definite."""
    c, info = lapack.dpotrf(A, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"{name} is not positive definite (LAPACK info {info})")
    return np.asarray(c)


def _cho_solve(c: Mat, B: Mat) -> Mat:
    """``A⁻¹ B`` from ``A``'s factor ``c`` of :func:`_cholesky` (LAPACK ``potrs``)."""
    X, info = lapack.dpotrs(c, B, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"potrs failed (LAPACK info {info})")
    return np.asarray(X)


def _s2(X: Mat) -> Sym2:
    """Rows ``(m, 4)`` (row-major 2 x 2) as a triple."""
    return X[:, 0], X[:, 1], X[:, 3]


def _flat2(a: Mat, b: Mat, c: Mat) -> Mat:
    return np.stack((a, b, b, c), axis=1)


def _inv2(a: Mat, b: Mat, c: Mat) -> Sym2:
    det = a * c - b * b
    return c / det, -b / det, a / det


def _mul2(x: Sym2, y: Sym2) -> tuple[Mat, Mat, Mat, Mat]:
    """``x y`` (not symmetric in general) as ``(p00, p01, p10, p11)``."""
    return (
        x[0] * y[0] + x[1] * y[1],
        x[0] * y[1] + x[1] * y[2],
        x[1] * y[0] + x[2] * y[1],
        x[1] * y[1] + x[2] * y[2],
    )


def _sandwich(R: Sym2, X: Sym2) -> Sym2:
    """``R X R`` for symmetric ``R``, ``X``."""
    p00, p01, p10, p11 = _mul2(R, X)
    return (
        p00 * R[0] + p01 * R[1],
        p00 * R[1] + p01 * R[2],
        p10 * R[1] + p11 * R[2],
    )


def _dot2(x: Sym2, y: Sym2) -> Mat:
    return x[0] * y[0] + 2.0 * x[1] * y[1] + x[2] * y[2]


def _eig2(a: Mat, b: Mat, c: Mat) -> tuple[Mat, Mat, Mat, Mat]:
    """Eigenvalues ``h + q >= h - q`` and ``(cos θ, sin θ)`` of the first eigenvector."""
    h = 0.5 * (a + c)
    d = 0.5 * (a - c)
    q = np.hypot(d, b)
    th = 0.5 * np.arctan2(b, d)
    return h + q, h - q, np.cos(th), np.sin(th)


def _negsum2(x: Sym2) -> Mat:
    """The sum of the negative eigenvalues: ``min_{0 ⪯ Y ⪯ I} <x, Y>``."""
    l1, l2, _, _ = _eig2(*x)
    return np.minimum(l1, 0.0) + np.minimum(l2, 0.0)


def _proj01(x: Sym2) -> Sym2:
    """The Frobenius projection onto ``{0 ⪯ Y ⪯ I}``: eigenvalues clipped to ``[0, 1]``."""
    l1, l2, cs, sn = _eig2(*x)
    l1 = np.clip(l1, 0.0, 1.0)
    l2 = np.clip(l2, 0.0, 1.0)
    return l1 * cs * cs + l2 * sn * sn, (l1 - l2) * cs * sn, l1 * sn * sn + l2 * cs * cs


def _sqrt2(a: Mat, b: Mat, c: Mat) -> Sym2:
    """``X^½`` of PSD 2 x 2 matrices (negative rounding clipped): ``(X + sqrt(det) I) / t``,
    ``t = sqrt(tr X + 2 sqrt(det))``."""
    a = np.maximum(a, 0.0)
    c = np.maximum(c, 0.0)
    s = np.sqrt(np.maximum(a * c - b * b, 0.0))
    t = np.sqrt(a + c + 2.0 * s)
    t = np.where(t > 0.0, t, 1.0)
    return (a + s) / t, b / t, (c + s) / t


class _Reduced(Protocol):
    """What the relaxation reads of its problem (:class:`~covnet.core.allocation.search_problem.\
_Problem`, which builds it): the reduced form (``P(Z) = Z⁻¹ T + P∞``, ``K``, ``C⁻¹``), ``P_d``
and its constants, the error model."""

    n: int
    s: NDArray[np.intp]
    D: Mat
    Y0: Mat
    Kmat: Mat
    Cinv: Mat
    P_inf: Mat
    T: Mat
    ctx: IntervalContext
    dc: DesiredConstants


class _Relaxation:
    """Lower bounds from the convex relaxation of a node in the reduced coordinates (``r = 2``).

    A node's completions have information ``Z ∈ [Z_lo, Z_hi]`` (Loewner, ``2 x 2``: ``Z_lo`` of
    ``I``, ``Z_hi`` of ``I ∪ U``) and covariance ``P = P∞ + K W Kᵀ`` with ``W = Z⁻¹ ∈ [Z_hi⁻¹,
    Z_lo⁻¹]``.  This set has 3 dimensions, where the Loewner interval ``[A, B]`` of the
    covariances has ``n(n+1)/2``: its minimum is much closer to the completions'.  For metrics
    convex in one of the two parametrisations ``V ∈ [V_lo, V_hi]`` (write ``V = V_lo + R X R``,
    ``R = (V_hi - V_lo)^½``, ``0 ⪯ X ⪯ I``), the value ``h(X_k)`` and gradient ``G_k`` at any
    point give (convexity, then the linear minimisation over ``{0 ⪯ Y ⪯ I}``)::

        min h >= h(X_k) - <G_k, X_k> + sum of the negative eigenvalues of G_k,

    evaluated along a projected-gradient descent; a node stops as soon as this exceeds the
    threshold (pruned) or ``h(X_k)`` is at most it (the relaxation cannot prune it).

    - **frobenius** in ``W``: ``h = ||M0 + K W Kᵀ||_F²`` (``M0 = P∞ - P_d``), gradient
      ``2 Kᵀ M K``; the bound is ``sqrt`` of the squared one;
    - **kl** in ``Z``: ``4 kl = c0 + tr(Q Z⁻¹) + <P_d[s, s], Z>`` (``Q = Kᵀ P_d⁻¹ K``,
      ``tr(P⁻¹ P_d) = tr(P_pred⁻¹ P_d) + <P_d[s, s], Z - C⁻¹>``), convex (``Z ↦ Z⁻¹`` is operator
      convex), gradient ``P_d[s, s] - Z⁻¹ Q Z⁻¹``;
    - **logdet** in ``W``: ``f = c1 + log det(I + V1 W) - ½ log det W`` (``V1 = Kᵀ (P∞ +
      P_d)⁻¹ K``, the determinant lemma and ``det P = det P∞[v, v] det W``), gradient
      ``(I + V1 W)⁻¹ V1 - ½ W⁻¹``; ``f = Σ φ(x_i)`` over the generalized eigenvalues with ``φ``
      convex on ``(0, 1 + sqrt 2]`` (``φ'' = 1/(2x²) - 1/(1 + x)²``), so ``f`` is convex (a
      spectral function of a convex ``φ``, of an affine image of ``W``) on the nodes whose
      ``x_max(P(I)) <= 1 + sqrt 2``;
    - **logdet** in ``Z`` on the other nodes where it is convex in ``Z``
      (:meth:`z_convex`: ``f = c1 + log det(Z + V1) - ½ log det Z``, the same ``φ`` of the
      eigenvalues ``y = 1/x`` of ``V1⁻¹ Z``, convex where ``y_max(Z(I ∪ U)) <= 1 + sqrt 2``),
      gradient ``(Z + V1)⁻¹ - ½ Z⁻¹``: the nodes with few sensors included (a large ``P(I)``,
      where ``W`` fails), which were most of logdet's tree at 32 sensors.  Nodes where neither
      holds are not refined.

    The iterations stop once the bound, after the final deflation below, exceeds the threshold
    (:meth:`_goal`, its pre-image); stopping before the deflation (as before) left every bound
    that had just reached the threshold deflated back below it.

    Rounding: the bound is deflated by the interval bound's model errors for the metric (the
    computed constants and the completion's computed ``P`` are within ``err``) and by a relative
    ``ROUND n² eps κ`` of every term it adds.  This holds in ``Z`` as in ``W``: ``K[s, :] = I``
    and ``P∞[s, s] = 0``, so ``W = P(S)[s, s]``, a principal submatrix, and ``cond Z = cond W <=
    cond P(S) <= κ`` (interlacing); ``Z + V1`` is no worse conditioned than ``I + V1 W``.
    """

    def __init__(self, prob: _Reduced, relaxation: Relaxation) -> None:
        self.prob = prob
        #: the closed form (the metric entry's :class:`~covnet.core.metrics.Relaxation`)
        self.form = relaxation.form
        #: strongly convex: the last levels from a table (:class:`_Leaves`)
        self.leaves = relaxation.leaves
        n, ctx = prob.n, prob.ctx
        D = prob.D
        s = prob.s
        self.rel = ROUND_REL * n * n * EPS * (ctx.kappa + 1.0)
        if self.form == "frobenius":
            self.M0 = prob.P_inf - D.reshape(n * n)
            self.Tt = np.ascontiguousarray(prob.T.T)
        elif self.form == "kl":
            L_inv, kappa_D = prob.dc.chol_inv()
            LK = L_inv @ prob.Kmat
            self.Q = _s2((LK.T @ LK).reshape(1, 4))
            Dss = D[np.ix_(s, s)]
            self.Dss = _s2(Dss.reshape(1, 4))
            Pinf = prob.P_inf.reshape(n, n)
            tr1 = float(((L_inv @ Pinf) @ L_inv.T).trace())
            self.c0 = tr1 + float((prob.Y0 * D).sum()) - float((Dss * prob.Cinv).sum()) - 2 * n
            self.kappa_D = kappa_D
        else:  # logdet
            Pinf = prob.P_inf.reshape(n, n)
            W = Pinf + D
            cw = _cholesky(W, "P∞ + P_d")
            V1 = prob.Kmat.T @ _cho_solve(cw, prob.Kmat)
            self.V1 = _s2(0.5 * (V1 + V1.T).reshape(1, 4))
            ld_W = 2.0 * float(np.log(np.diag(cw)).sum())
            v = np.ones(n, dtype=bool)
            v[s] = False
            if v.any():
                cv = _cholesky(Pinf[np.ix_(v, v)], "P∞[v, v]")
                ld_v = 2.0 * float(np.log(np.diag(cv)).sum())
            else:
                ld_v = 0.0
            ld_D = 2.0 * float(np.log(np.diag(np.linalg.cholesky(D))).sum())
            self.c1 = ld_W - n * math.log(2.0) - 0.5 * ld_v - 0.5 * ld_D
            self.mag = abs(ld_W) + abs(ld_v) + abs(ld_D) + n

    def _h(self, V: Sym2, zform: bool = False) -> tuple[Mat, Sym2]:
        """The convex objective and its gradient at ``V`` (``W`` or ``Z``; logdet with
        ``zform``: in ``Z``)."""
        if zform:  # logdet in Z: c1 + log det(Z + V1) - ½ log det Z
            a, b, c = V
            v0, v1, v2 = self.V1
            e0, e1, e2 = a + v0, b + v1, c + v2
            detE = e0 * e2 - e1 * e1
            detZ = a * c - b * b
            g = self.c1 + np.log(detE) - 0.5 * np.log(detZ)
            Ei = (e2 / detE, -e1 / detE, e0 / detE)
            Zi = _inv2(a, b, c)
            return g, (Ei[0] - 0.5 * Zi[0], Ei[1] - 0.5 * Zi[1], Ei[2] - 0.5 * Zi[2])
        if self.form == "frobenius":
            M = _flat2(*V) @ self.prob.T
            M += self.M0
            g = np.einsum("mk,mk->m", M, M)
            G4 = M @ self.Tt
            return g, (2.0 * G4[:, 0], G4[:, 1] + G4[:, 2], 2.0 * G4[:, 3])
        if self.form == "kl":
            Vi = _inv2(*V)
            QVi = _sandwich(Vi, self.Q)  # Z⁻¹ Q Z⁻¹
            t = _dot2(self.Q, Vi) + _dot2(self.Dss, V)
            g = 0.25 * (self.c0 + t)
            return g, (
                0.25 * (self.Dss[0] - QVi[0]),
                0.25 * (self.Dss[1] - QVi[1]),
                0.25 * (self.Dss[2] - QVi[2]),
            )
        # logdet: c1 + log det(I + V1 W) - ½ log det W
        a, b, c = V
        v0, v1, v2 = self.V1
        p00, p01, p10, p11 = _mul2(self.V1, V)
        p00 = p00 + 1.0
        p11 = p11 + 1.0
        det1 = p00 * p11 - p01 * p10
        detW = a * c - b * b
        g = self.c1 + np.log(det1) - 0.5 * np.log(detW)
        # (I + V1 W)⁻¹ V1 = adj(I + V1 W) V1 / det1
        i00, i01, i10, i11 = p11 / det1, -p01 / det1, -p10 / det1, p00 / det1
        g00 = i00 * v0 + i01 * v1
        g01 = 0.5 * ((i00 * v1 + i01 * v2) + (i10 * v0 + i11 * v1))
        g11 = i10 * v1 + i11 * v2
        Wi = _inv2(a, b, c)
        return g, (g00 - 0.5 * Wi[0], g01 - 0.5 * Wi[1], g11 - 0.5 * Wi[2])

    def bound(
        self,
        Z_lo: Mat,
        Z_hi: Mat,
        tau: float,
        zform: bool = False,
        stop: Callable[[], bool] | None = None,
    ) -> Mat:
        """Lower bounds ``(m,)`` of the metric over the nodes with information ``[Z_lo, Z_hi]``
        (rows ``(m, 4)``); ``-inf`` where nothing is proven.  ``zform`` (logdet only, on rows
        where :meth:`z_convex` holds): the objective in ``Z``.  ``stop`` (a time limit): the
        iterations end once it says so, after the first (every iteration's tangent plane is a
        valid bound, so an early end only loosens it)."""
        m = Z_lo.shape[0]
        out = np.full(m, -np.inf)
        if m == 0:
            return out
        with np.errstate(all="ignore"):
            if self.form == "kl" or zform:
                lo, hi = _s2(Z_lo), _s2(Z_hi)
            else:
                lo, hi = _inv2(*_s2(Z_hi)), _inv2(*_s2(Z_lo))
            R = _sqrt2(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2])
            goal = self._goal(tau)
            idx = np.arange(m)
            X: Sym2 = (np.full(m, 0.5), np.zeros(m), np.full(m, 0.5))
            step = np.ones(m)
            h_x, G_x = self._hx(lo, R, X, zform)
            for _ in range(RELAX_ITERS):
                lb = h_x - _dot2(G_x, X) + _negsum2(G_x)
                lb_safe = self._deflate(lb, h_x, G_x)
                out[idx] = np.fmax(out[idx], lb_safe)
                if math.isinf(goal):  # no threshold: the best bound the iterations give
                    live = np.isfinite(h_x)
                else:
                    live = ~((lb_safe > goal) | (h_x <= goal) | ~np.isfinite(h_x))
                if not live.any() or (stop is not None and stop()):
                    break
                keep = np.flatnonzero(live)
                idx = idx[keep]
                lo = _take(lo, keep)
                R = _take(R, keep)
                X, G_x, h_x, step = _take(X, keep), _take(G_x, keep), h_x[keep], step[keep]
                gn = np.sqrt(_dot2(G_x, G_x))
                s_ = step / np.where(gn > 0.0, gn, 1.0)
                Xn = _proj01((X[0] - s_ * G_x[0], X[1] - s_ * G_x[1], X[2] - s_ * G_x[2]))
                h_n, G_n = self._hx(lo, R, Xn, zform)
                ok = h_n < h_x
                X = _where(ok, Xn, X)
                G_x = _where(ok, G_n, G_x)
                h_x = np.where(ok, h_n, h_x)
                step = np.where(ok, step * 1.5, step * 0.3)
        return self._final(out)

    def value(self, Z: Mat) -> Mat:
        """The metric of the covariances of the information rows ``Z`` ``(m, 4)`` from the
        reduced formulas above (greedy's working values)."""
        V = _s2(Z) if self.form == "kl" else _inv2(*_s2(Z))
        g, _ = self._h(V)
        return np.sqrt(g) if self.form == "frobenius" else g

    def z_convex(self, Z_hi: Mat) -> NDArray[np.bool_]:
        """logdet: rows whose interval ``Z ⪯ Z_hi`` keeps ``f`` convex in ``Z``.

        In ``Z`` (``W = Z⁻¹``, ``det W = 1 / det Z``) the objective is ``c1 + log det(I + V1 Z⁻¹)
        + ½ log det Z = c1 + log det(Z + V1) - ½ log det Z = c1' + Σ φ(y_i)``, ``φ(y) = log(1 + y)
        - ½ log y`` (the same ``φ``), ``y_i`` the eigenvalues of ``Y = V1^-½ Z V1^-½`` (affine in
        ``Z``).  ``φ`` is convex on ``(0, 1 + sqrt 2]``, so ``f`` is convex (a spectral function
        of a convex ``φ``) on ``{Z : 0 ≺ Z, λmax(Y) <= 1 + sqrt 2}``, which holds on the whole
        interval when it holds at ``Z_hi`` (``Z ⪯ Z_hi`` gives ``Y(Z) ⪯ Y(Z_hi)``).
        ``λmax(V1⁻¹ Z_hi)`` is computed in closed form; a relative margin ``1e-6 + 4 ρ``
        (``ρ = n err / λmin``: the computed ``Z_hi`` against the completions') covers its
        rounding.  (Where neither this nor ``x_max(P(I)) <= 1 + sqrt 2`` holds, nothing is
        refined.)"""
        y_max, pd = self.y_max(Z_hi)
        with np.errstate(all="ignore"):
            rho = self.prob.n * self.prob.ctx.err / self.prob.ctx.lam_min
            ok = y_max * (1.0 + 1e-6 + 4.0 * rho) < LOGDET_CONVEX
        return np.asarray(ok & np.isfinite(y_max) & pd, dtype=bool)

    def y_max(self, Z: Mat) -> tuple[Mat, NDArray[np.bool_]]:
        """logdet: ``λmax(V1⁻¹ Z)`` of the rows ``Z`` ``(m, 4)`` (closed form, the larger root of
        ``det(Z - y V1) = 0``; its rounding is at most a relative ``1e-7``: ``sqrt`` of the
        discriminant's), and whether ``det Z > 0``."""
        a, b, c = _s2(Z)
        v0, v1, v2 = self.V1
        with np.errstate(all="ignore"):
            qa = v0 * v2 - v1 * v1
            qb = -(a * v2 + c * v0 - 2.0 * b * v1)
            qc = a * c - b * b
            disc = np.sqrt(np.maximum(qb * qb - 4.0 * qa * qc, 0.0))
            y = (-qb + disc) / (2.0 * qa)
        return np.asarray(y, dtype=np.float64), np.asarray(qc > 0.0, dtype=bool)

    def _hx(self, lo: Sym2, R: Sym2, X: Sym2, zform: bool) -> tuple[Mat, Sym2]:
        """``h`` and its ``X``-gradient ``R ∇h R`` at ``V = V_lo + R X R``."""
        RXR = _sandwich(R, X)
        V = (lo[0] + RXR[0], lo[1] + RXR[1], lo[2] + RXR[2])
        g, G = self._h(V, zform)
        return g, _sandwich(R, G)

    def _goal(self, tau: float) -> float:
        """The threshold in ``h``'s units: the least ``h``-bound whose :meth:`_final` exceeds
        ``tau`` (the model errors added back; frobenius: squared), slightly raised.  Only the
        iterations' stopping rule uses it: a node stops once its bound, *after* the deflation of
        :meth:`_final`, would prune it.  (Stopping at ``tau`` itself left every such bound
        deflated back below ``tau``, so only bounds far above it could prune.)"""
        if not math.isfinite(tau):
            return tau
        a, c = self._final_affine()
        if a <= 0.0:
            return math.inf
        t = (tau + c) / a
        if self.form == "frobenius":
            return t * t * (1.0 + 1e-12) if t >= 0.0 else -math.inf
        return t + 1e-12 * abs(t)

    def _final_affine(self) -> tuple[float, float]:
        """``(a, c)`` with :meth:`_final`'s ``v = a x - c``, ``x`` the ``h``-bound (frobenius:
        its square root)."""
        prob, ctx, n = self.prob, self.prob.ctx, self.prob.n
        rel = ROUND * n * EPS
        if self.form == "frobenius":
            return 1.0 - rel, 3.0 * n * ctx.err + rel * ctx.scale
        rho = n * ctx.err / ctx.lam_min
        if self.form == "kl":
            tr_inv = self.kappa_D / prob.dc.trace
            mag = tr_inv * ctx.lam_max + prob.dc.trace / ctx.lam_min + 2.0 * n
            kap = ROUND * n * n * n * EPS * (ctx.kappa + self.kappa_D)
            return 1.0 - rel - 3.0 * rho, 3.0 * rho * n + kap * mag
        kap = ROUND * n * n * n * EPS * (ctx.kappa + 1.0)
        return 1.0 - rel, 2.0 * n * rho + kap * (self.mag + abs(self.c1))

    def _deflate(self, lb: Mat, h: Mat, G: Sym2) -> Mat:
        """``lb`` less the rounding of its terms (relative ``rel`` of ``|h|`` and of the
        gradient's size), in ``h``'s units."""
        gn = np.sqrt(_dot2(G, G))
        return np.asarray(lb - self.rel * (np.abs(h) + 4.0 * gn + 1.0), dtype=np.float64)

    def _final(self, lb: Mat) -> Mat:
        """From ``h``'s units to the metric's, less the model errors (the interval bounds'):
        frobenius ``a sqrt(max(lb, 0)) - c``, kl and logdet ``a lb - c`` (:meth:`_final_affine`;
        kl: ``lb (1 - rel) - (3 ρ (lb + n) + κ' mag)``, logdet ``lb (1 - rel) - (2 n ρ + κ'
        (mag + |c1|))``, ``ρ = n err / λmin``).

        The bound is ``a x_true - c <= f`` with ``x_true >= x``, the node's true ``h``-minimum:
        it follows from ``x`` only where ``a > 0``.  Where the model errors swamp it (``a <= 0``:
        kl's ``3 ρ >= 1 - rel`` on an ill-conditioned problem, ``ρ = n err / λmin``), ``a x -
        c`` is no bound at all (a very negative ``x`` made it a huge positive number, and a
        search certified a subset at twice the optimum as optimal): then there is none,
        ``-inf``, as :meth:`_goal` already says."""
        a, c = self._final_affine()
        if a <= 0.0:
            return np.full(np.shape(lb), -np.inf)
        x = np.sqrt(np.maximum(lb, 0.0)) if self.form == "frobenius" else lb
        v = a * x - c
        return np.where(np.isnan(v), -np.inf, v)


def _take(x: Sym2, rows: NDArray[np.intp]) -> Sym2:
    return x[0][rows], x[1][rows], x[2][rows]


def _where(ok: NDArray[np.bool_], x: Sym2, y: Sym2) -> Sym2:
    return np.where(ok, x[0], y[0]), np.where(ok, x[1], y[1]), np.where(ok, x[2], y[2])
