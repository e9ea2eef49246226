"""The last levels of a kl, frobenius or logdet branch-and-bound tree from a table
(:class:`_Leaves`).

**Table of the last levels** (kl, frobenius, logdet; :class:`_Leaves`): the completions of a
node at depth ``d0 = m - LEAF_LEVELS`` are ``Z(I) + T_t`` over a table of the ``2^LEAF_LEVELS``
subset sums of the last sensors, and, the metric being strongly convex (kl in ``Z`` on bounded
sets, frobenius² in ``W``, logdet in ``Z`` where ``y_max(Z_all) < 1 + sqrt 2``), every
completion that can still be ``<= τ`` lies in a small ball around the continuous minimiser,
found by a k-d tree query: so the last levels cost one query per node and the candidates in the
ball, not a subtree.  Those are recorded with a valid bound as the tree's own candidates, and a
completion outside the ball is above ``τ``, so the exactness argument
(:mod:`covnet.core.allocation.search`) is unchanged.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation.relaxation import (
    LOGDET_CONVEX,
    _dot2,
    _eig2,
    _inv2,
    _s2,
    _sandwich,
    _sqrt2,
)
from covnet.core.gaussian import Mat

if TYPE_CHECKING:
    from covnet.core.allocation.search_problem import _Problem


class _Leaves:
    """The last ``u`` levels of a kl, frobenius or logdet tree at once: a table of completions
    and a ball.

    kl in ``Z`` (:class:`_Relaxation`) is ``h(Z) = ¼ (c0 + <Q, Z⁻¹> + <P_d[s, s], Z>)``, convex
    on ``Z ≻ 0``, and on the paper-like problems its minimum over subsets is within about
    ``1e-8`` of its continuous minimum: every node whose interval contains the continuous
    minimiser survives every continuous bound, and the tree enumerates the completions near it
    one level at a time.  Instead, below depth ``d0 = m - u`` the completions of a node ``I`` are
    ``Z(I) + T_t``, ``T_t`` the sums of the subsets ``t`` of the last ``u`` sensors (a table of
    ``2^u`` rows built once), and those that can still be ``<= τ`` lie in a ball:

    **Strong convexity.**  ``∇²h(Z)[H, H] = ½ tr(Q Z⁻¹ H Z⁻¹ H Z⁻¹) = ½ tr(Q^½ B Bᵀ Q^½)``,
    ``B = Z⁻¹ H Z^-½``, ``>= ½ λmin(Q) ||B||_F² >= ½ λmin(Q) λmax(Z)⁻³ ||H||_F²``.  So on any
    convex set where ``λmax(Z) <= Λ``, ``h`` is ``μ = ½ λmin(Q) Λ⁻³``-strongly convex, and for
    ``Z0`` there (value ``h0``, gradient ``g0``)::

        h(Z) >= h0 + <g0, Z - Z0> + (μ/2) ||Z - Z0||²,   so   h(Z) <= τ'  ⟹
        ||Z - c|| <= r,  c = Z0 - g0/μ,  r² = 2 (τ' - h0)/μ + ||g0||²/μ²

    (Frobenius norm on symmetric ``2 x 2``: coordinates ``(a, √2 b, c)``).  ``Z0`` is the
    continuous minimiser (``Z P_d[s, s] Z = Q``, solved in closed form; only ``g0`` depends on
    how well); ``Λ`` first ``max(λmax(Z_all), λmax(Z0))`` (every completion is ``⪯ Z_all``, and
    ``λmax`` is convex, so this bounds it on the segments from ``Z0`` too), then, twice,
    ``max(λmax(Z0), λmax(c) + r)`` of the previous ball: every completion with ``h <= τ'`` is
    in that ball, where ``λmax <= λmax(c) + r`` (Weyl), and again convexity covers the segments
    from ``Z0``.  The computed gradient's error ``g_err`` (its two terms cancel at ``Z0``) moves
    the center by at most ``g_err / μ``: added to ``r``.

    **frobenius** (:class:`_Relaxation`: ``h(W) = ||M0 + K W Kᵀ||_F²``, the square of the
    metric, ``W = Z⁻¹``) is a quadratic in ``W`` with ``∇²h[H, H] = 2 ||K H Kᵀ||_F² >= 2
    λmin(KᵀK)² ||H||_F²`` everywhere, so the same inequality, with ``Z0`` replaced by the
    unconstrained minimiser ``W0 = -(KᵀK)⁻¹ Kᵀ M0 K (KᵀK)⁻¹`` and ``μ = 2 λmin(KᵀK)²``, puts
    every ``W`` with ``h(W) <= τ'`` in a ball ``||W - c|| <= r``.  For ``c ≻ 0`` and a
    completion ``Z = W⁻¹ ⪯ Z_all``: ``||Z - c⁻¹||_F = ||W⁻¹ (c - W) c⁻¹||_F <= λmax(Z) r /
    λmin(c)``, with ``λmax(Z) <= Λ``, first ``λmax(Z_all)``, then (twice) ``λmax(c⁻¹)`` plus the
    previous radius: the ball in ``Z`` that is queried.

    **logdet** in ``Z`` (:meth:`_Relaxation.z_convex`: ``h = c1 + log det(Z + V1) - ½ log det
    Z``): ``∇²h[H, H] = ½ ||M||_F² - ||A M Aᵀ||_F²`` with ``M = Z^-½ H Z^-½``, ``A = (Z +
    V1)^-½ Z^½``, ``||A||_2² = s = y_max / (1 + y_max)`` (``y`` the eigenvalues of ``V1⁻¹ Z``), so
    ``∇²h >= (½ - s²) / λmax(Z)²``: strongly convex on the convex set ``{λmax(Z) <= Λ,
    y_max(Z) <= Y}`` when ``Y < 1 + sqrt 2``.  Every completion is in it with ``Λ =
    max(λmax(Z_all), λmax(V1))``, ``Y = max(1, y_max(Z_all))`` (both monotone in the Loewner
    order and convex), and so is ``Z0 = V1``, the stationary point (``(Z + V1)⁻¹ = ½ Z⁻¹``,
    ``y = 1``); then the same ball, refined twice (``λmax <= λmax(c) + r``, ``y_max <=
    y_max(c) + r / λmin(V1)`` on it).  No ball (the tree goes on) when ``y_max(Z_all) >= 1 +
    sqrt 2``.

    **Threshold.**  ``τ' = (goal(τ) + rel) / (1 - rel)`` (:meth:`_Relaxation._goal`, the
    relaxation's rounding ``rel``): a completion whose exact ``h`` exceeds it has a relaxation
    bound (the degenerate interval ``[Z, Z]``: ``h`` deflated) above ``τ``, so its computed value
    is above ``τ`` and it is pruned exactly as the tree would prune it; ``h0``, ``g0``, ``r`` and
    the projections below carry a relative ``1e-6`` of slack for their own rounding.  The
    completions inside are recorded as candidates with that degenerate relaxation bound (``<=``
    their computed value); ``t = 0`` (``I`` itself) was recorded when its last sensor was
    included.  Pruned completions are above ``τ`` (the certified bound takes ``τ``).

    The table's points ``(a, √2 b, c)`` are in a k-d tree (``scipy.spatial.cKDTree``); a node's
    query is the ball around ``c - Z(I)`` (radius widened by a relative ``1e-6`` of the
    coordinates for their rounding), then the budget (``|t| <= K - |I|``).
    """

    def __init__(self, prob: _Problem, d0: int) -> None:
        relax = prob.relax
        assert relax is not None and relax.leaves
        self.prob, self.relax, self.d0 = prob, relax, d0
        u = prob.m - d0
        self.u = u
        T = np.zeros((1, 4))
        cnt = np.zeros(1, dtype=np.int64)
        for j in range(d0, prob.m):
            T = np.concatenate((T, T + prob.S[j]))
            cnt = np.concatenate((cnt, cnt + 1))
        X = np.stack((T[:, 0], math.sqrt(2.0) * T[:, 1], T[:, 3]), axis=1)
        from scipy.spatial import cKDTree  # here only: the start-up of covnet.core stays light

        self.tree = cKDTree(X, leafsize=32, balanced_tree=False)
        self._canon: tuple[bytes, NDArray[np.bool_]] | None = None
        self._ball_of: tuple[float, tuple[NDArray[np.float64], float] | None] | None = None
        self.Xmax = float(np.abs(X).max())
        self.T, self.cnt = T, cnt
        self.lam_all = _lmax(prob.base + prob.suffix[0])
        if relax.form == "frobenius":
            self._frobenius()
            return
        if relax.form == "logdet":
            self._logdet()
            return
        # the continuous minimiser: Z Dss Z = Q  ⟺  Z = Dss^-½ (Dss^½ Q Dss^½)^½ Dss^-½
        Dh = _sqrt2(*relax.Dss)
        Dhi = _inv2(*Dh)
        M = _sqrt2(*_sandwich(Dh, relax.Q))
        Z0 = _sandwich(Dhi, M)
        self.Z0 = np.array([Z0[0][0], Z0[1][0], Z0[1][0], Z0[2][0]])
        self._anchor(self.Z0)
        # the computed gradient ¼ (Dss - Z0⁻¹ Q Z0⁻¹) (two terms that cancel at Z0) is within a
        # relative rel of their sizes
        Zi = _inv2(*_s2(self.Z0[None]))
        QZ = _sandwich(Zi, relax.Q)
        size = float(np.sqrt(_dot2(relax.Dss, relax.Dss))[0] + np.sqrt(_dot2(QZ, QZ))[0])
        self.g_err = 0.25 * size * (relax.rel + 1e-12)
        self.lmin_Q = float(_eig2(*relax.Q)[1][0])
        self.lmax0 = max(self.lam_all, _lmax(self.Z0))

    def _frobenius(self) -> None:
        """The constants of the frobenius ball (class docstring)."""
        relax, prob = self.relax, self.prob
        n = prob.n
        K = prob.Kmat
        KtK = K.T @ K
        KtK = 0.5 * (KtK + KtK.T)
        A = np.linalg.inv(KtK)
        M0 = relax.M0.reshape(n, n)
        W0 = -(A @ (K.T @ M0 @ K) @ A)
        W0 = 0.5 * (W0 + W0.T)
        self.W0 = W0.reshape(4)
        self._anchor(self.W0)
        # the gradient 2 Kᵀ (M0 + K W0 Kᵀ) K: two terms that cancel at W0
        size = 2.0 * (float(np.linalg.norm(K.T @ M0 @ K)) + float(np.linalg.norm(KtK @ W0 @ KtK)))
        self.g_err = size * (relax.rel + 1e-12)
        self.mu = 2.0 * float(np.linalg.eigvalsh(KtK)[0]) ** 2 * (1.0 - 1e-6)

    def _anchor(self, V: Mat, zform: bool = False) -> None:
        """``h0`` (rounded down), ``g0`` (``(a, b, c)``) and ``|g0|`` (rounded up) of the
        objective at the row-major ``2 x 2`` point ``V``: the anchor of the balls."""
        relax = self.relax
        with np.errstate(all="ignore"):
            h0, g0 = relax._h(_s2(V[None]), zform=zform)
        self.h0 = float(h0[0]) - relax.rel * (abs(float(h0[0])) + 1.0)
        g = np.array([g0[0][0], g0[1][0], g0[2][0]])
        self.g0 = g
        self.gn = float(np.sqrt(g[0] ** 2 + 2.0 * g[1] ** 2 + g[2] ** 2)) * (1.0 + 1e-6)

    def _threshold(self, tau: float) -> float | None:
        """``τ'`` of ``τ`` (class docstring), or None where there is none: also where the
        relaxation's relative rounding ``rel = 64 n² eps (κ + 1)`` reaches 1 (``κ >~ 4e12``),
        beyond which ``(goal + rel) / (1 - rel)`` is no bound (it went negative, every ball was
        empty, and the exact search dropped every completion below the table's depth: a wrong
        subset certified optimal)."""
        if not math.isfinite(tau):
            return None
        relax = self.relax
        if not relax.rel < 1.0:
            return None
        tp = (relax._goal(tau) + relax.rel) / (1.0 - relax.rel)
        return tp if math.isfinite(tp) else None

    def _strong_ball(self, x0: Mat, mu: float, tp: float) -> tuple[Mat, float] | None:
        """Center (row-major ``2 x 2``) and radius of the ball holding every point with
        ``h <= tp`` of a ``mu``-strongly convex ``h`` anchored at ``x0`` (:meth:`_anchor`),
        the computed gradient's error included; None: no point reaches ``tp``."""
        gn = self.gn + self.g_err
        r2 = 2.0 * (tp - self.h0) / mu + (gn / mu) ** 2
        if r2 < 0.0:
            return None
        r = math.sqrt(r2) * (1.0 + 1e-6) + self.g_err / mu
        c = x0 - np.array([self.g0[0], self.g0[1], self.g0[1], self.g0[2]]) / mu
        return c, r

    def ball(self, tau: float) -> tuple[NDArray[np.float64], float] | None:
        """The ball of the completions that can still reach ``tau`` (center in the table's
        coordinates, radius; see the per-metric methods); the last one is kept, as ``tau``
        changes only when the incumbent does."""
        if self._ball_of is not None and self._ball_of[0] == tau:
            return self._ball_of[1]
        if self.relax.form == "frobenius":
            got = self._frobenius_ball(tau)
        elif self.relax.form == "logdet":
            got = self._logdet_ball(tau)
        else:
            got = self._kl_ball(tau)
        self._ball_of = (tau, got)
        return got

    def _logdet(self) -> None:
        """The constants of the logdet ball (class docstring)."""
        relax, prob = self.relax, self.prob
        V1 = np.array([relax.V1[0][0], relax.V1[1][0], relax.V1[1][0], relax.V1[2][0]])
        self.Z0 = V1  # the stationary point: (Z + V1)⁻¹ = ½ Z⁻¹
        self._anchor(V1, zform=True)
        Vi = _inv2(*_s2(V1[None]))
        size = float(np.sqrt(_dot2(Vi, Vi))[0])  # (2 V1)⁻¹ - ½ V1⁻¹: two terms of this size
        self.g_err = size * (relax.rel + 1e-12)
        self.lam_v = _lmax(V1)
        self.lmin_v = _lmin_below(V1)
        Z_all = prob.base + prob.suffix[0]
        y_all, pd = relax.y_max(Z_all[None])
        rho = prob.n * prob.ctx.err / prob.ctx.lam_min
        self.y_all = max(1.0, float(y_all[0]) * (1.0 + 1e-6 + 4.0 * rho))
        if not (bool(pd[0]) and math.isfinite(self.y_all)):
            self.y_all = math.inf

    def _logdet_ball(self, tau: float) -> tuple[NDArray[np.float64], float] | None:
        """The ball of :meth:`ball` for logdet in ``Z`` (class docstring)."""
        relax = self.relax
        tp = self._threshold(tau) if self.lmin_v > 0.0 else None
        if tp is None:
            return None
        lam = max(self.lam_all, self.lam_v)
        Y = self.y_all
        best: tuple[NDArray[np.float64], float] | None = None
        for _ in range(3):
            if not Y < LOGDET_CONVEX:
                return best
            s_ = Y / (1.0 + Y)
            mu = (0.5 - s_ * s_) / (lam * lam) * (1.0 - 1e-6)
            if not mu > 0.0:
                return best
            got = self._strong_ball(self.Z0, mu, tp)
            if got is None:
                return NO_BALL
            c, r = got
            cx = _coords(c)
            if best is None or r < best[1]:
                best = (cx, r)
            # on the ball: λmax <= λmax(c) + r, y_max <= y_max(c) + r / λmin(V1)
            yc, _ = relax.y_max(c[None])
            new_lam = max(self.lam_v, _lmax(c) + r * (1.0 + 1e-6))
            new_y = max(1.0, (float(yc[0]) + r / self.lmin_v) * (1.0 + 1e-6))
            if not (new_lam < lam or new_y < Y):
                break
            lam, Y = min(lam, new_lam), min(Y, new_y)
        return best

    def _frobenius_ball(self, tau: float) -> tuple[NDArray[np.float64], float] | None:
        """The ball in ``Z`` of :meth:`ball` for frobenius (class docstring)."""
        tp = self._threshold(tau) if self.mu > 0.0 else None
        if tp is None:
            return None
        got = self._strong_ball(self.W0, self.mu, tp)
        if got is None:
            return NO_BALL
        c, r = got
        # λmin(c) from below (the 2 x 2 closed form, rounded down a little)
        a, b, d = float(c[0]), float(c[1]), float(c[3])
        lmin_c = _lmin_below(c) - 1e-12 * (abs(a) + abs(b) + abs(d))
        if not lmin_c > 0.0:
            return None
        ci = _inv2(np.array([a]), np.array([b]), np.array([d]))
        zc = np.array([float(ci[0][0]), float(ci[1][0]), float(ci[1][0]), float(ci[2][0])])
        lam_ci = _lmax(zc)
        lam = self.lam_all
        rz = math.inf
        for _ in range(3):
            rz = min(rz, lam * r / lmin_c * (1.0 + 1e-6))
            new = lam_ci + rz
            if not new < lam:
                break
            lam = new
        cx = _coords(zc)
        # the computed c⁻¹ is within a relative 1e-9 of the exact one (slack in the radius)
        return cx, rz + 1e-9 * float(np.abs(cx).max())

    def _kl_ball(self, tau: float) -> tuple[NDArray[np.float64], float] | None:
        """Center ``(a, √2 b, c)`` and radius of the ball holding every completion ``Z`` with
        ``h(Z) <= τ'`` (radius ``-1``: none can; ``None``: no ball, e.g. ``τ = inf`` or
        ``λmin(Q) <= 0`` from rounding: then the tree goes on below ``d0``)."""
        tp = self._threshold(tau) if self.lmin_Q > 0.0 else None
        if tp is None:
            return None
        lam = self.lmax0
        best: tuple[NDArray[np.float64], float] | None = None
        for _ in range(3):
            mu = 0.5 * self.lmin_Q / lam**3 * (1.0 - 1e-6)
            got = self._strong_ball(self.Z0, mu, tp)
            if got is None:
                return NO_BALL  # nothing can reach τ'
            c, r = got
            cx = _coords(c)
            if best is None or r < best[1]:
                best = (cx, r)
            # every completion with h <= τ' is in this ball: λmax <= λmax(c) + r there, and
            # on the segments from Z0 to it (λmax is convex)
            new = max(_lmax(self.Z0), _lmax(c) + r * (1.0 + 1e-6))
            if not new < lam:
                break
            lam = new
        return best

    def leaves(
        self,
        Z: Mat,
        k: NDArray[np.int64],
        inc: NDArray[np.uint8],
        tau: float,
        K: int | None = None,
        same: NDArray[np.bool_] | None = None,
    ) -> tuple[NDArray[np.uint8], Mat, int]:
        """The completions of the nodes (``Z`` ``(c, 4)``, ``k``, packed ``inc``) inside the
        ball, as packed rows with their bounds; and how many table rows were looked at.
        ``K``: the budget (default the problem's); ``same``: keep only the canonical
        completions of identical sensors (:mod:`covnet.core.allocation.tie_rule`: position
        ``p`` included only with ``p - 1``, ``same[p]`` saying the two are identical)."""
        prob = self.prob
        got = self.ball(tau)
        empty = (np.zeros((0, inc.shape[1]), dtype=np.uint8), np.zeros(0), 0)
        if got is None:
            return empty
        cx, r = got
        if r < 0.0:
            return empty
        Zx = np.stack((Z[:, 0], math.sqrt(2.0) * Z[:, 1], Z[:, 3]), axis=1)
        q = cx[None] - Zx  # the ball's center relative to each node
        # slack for the rounding of q and of the table's coordinates
        rad = r * (1.0 + 1e-6) + 1e-6 * (np.sqrt((q * q).sum(axis=1)) + self.Xmax)
        hits = self.tree.query_ball_point(q, rad, eps=0.0, return_sorted=False)
        n = np.array([len(h) for h in hits], dtype=np.intp)
        tot = int(n.sum())
        if tot == 0:
            return empty
        node = np.repeat(np.arange(Z.shape[0]), n)
        t = np.concatenate([np.asarray(h, dtype=np.intp) for h in hits])
        ok = (t != 0) & (self.cnt[t] <= (prob.K if K is None else K) - k[node])
        if same is not None and same[self.d0 :].any():
            ok &= self._canonical(same)[t]
            if same[self.d0]:  # the table's first sensor needs the tree's last one
                d = self.d0 - 1
                prev = ((inc[:, d >> 3] >> np.uint8(d & 7)) & np.uint8(1)).astype(bool)
                ok &= prev[node] | ((t & 1) == 0)
        return self._rows(Z, inc, node[ok], t[ok], tau, tot)

    def _canonical(self, same: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Table rows with no position ``p`` (both in the table) included without ``p - 1``
        where ``same[p]``."""
        key = same[self.d0 :].tobytes()
        if self._canon is not None and self._canon[0] == key:
            return self._canon[1]
        t = np.arange(self.T.shape[0])
        ok = np.ones(t.size, dtype=bool)
        for q in range(1, self.u):
            if same[self.d0 + q]:
                ok &= ((t >> q) & 1 == 0) | ((t >> (q - 1)) & 1 == 1)
        self._canon = (key, ok)
        return ok

    def _rows(
        self,
        Z: Mat,
        inc: NDArray[np.uint8],
        node: NDArray[np.intp],
        t: NDArray[np.intp],
        tau: float,
        looked: int,
    ) -> tuple[NDArray[np.uint8], Mat, int]:
        if node.size == 0:
            return np.zeros((0, inc.shape[1]), dtype=np.uint8), np.zeros(0), looked
        Zt = Z[node] + self.T[t]
        est = self.relax.bound(Zt, Zt, tau)
        bits = ((t[:, None] >> np.arange(self.u)) & 1).astype(bool)
        rows = self.prob.unpack(inc[node])
        rows[:, self.d0 :] |= bits
        packed = np.packbits(rows, axis=1, bitorder="little")
        return packed, est, looked


NO_BALL: tuple[NDArray[np.float64], float] = (np.zeros(3), -1.0)
"""What :meth:`_Leaves.ball` returns when no completion can reach the threshold."""


def _coords(Z: Mat) -> NDArray[np.float64]:
    """The k-d tree coordinates ``(a, √2 b, c)`` of one row-major ``2 x 2`` ``Z`` (the
    Frobenius norm of symmetric matrices as the Euclidean one)."""
    return np.array([Z[0], math.sqrt(2.0) * Z[1], Z[3]])


def _lmin_below(Z: Mat) -> float:
    """The smallest eigenvalue of one row-major symmetric ``2 x 2`` ``Z``, rounded down a
    little (closed form)."""
    a, b, c = float(Z[0]), float(Z[1]), float(Z[3])
    return (0.5 * (a + c) - math.hypot(0.5 * (a - c), b)) * (1.0 - 1e-9)


def _lmax(Z: Mat) -> float:
    """The largest eigenvalue of one row-major ``2 x 2`` ``Z``, rounded up a little."""
    a, b, c = float(Z[0]), float(0.5 * (Z[1] + Z[2])), float(Z[3])
    h, q = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    return (h + q) * (1.0 + 1e-9) + 1e-300
