"""OSPA and GOSPA distances between two finite sets of vectors (e.g. target positions).

``X = {x_1..x_m}`` (truth), ``Y = {y_1..y_n}`` (estimates), rows of ``(m, d)`` and ``(n, d)``
arrays; ``d(x, y) = ‖x − y‖₂``, ``d^(c)(x, y) = min(c, d(x, y))``; cut-off ``c > 0``, order
``p ≥ 1``.  Both minimisations over assignments are solved exactly with
``scipy.optimize.linear_sum_assignment`` on the ``m × n`` matrix of ``d^(c)(x_i, y_j)^p``.

**OSPA** (Schuhmacher, Vo & Vo 2008), for ``m ≤ n`` (else swap ``X`` and ``Y``)::

    d̄_p^(c)(X, Y) = ( (1/n) ( min_π Σ_{i=1}^m d^(c)(x_i, y_π(i))^p + c^p (n − m) ) )^{1/p}

``0`` if both sets are empty, ``c`` if exactly one is.  A metric; always in ``[0, c]``.

**GOSPA** with ``α = 2`` (Rahmathullah, García-Fernández & Svensson 2017)::

    d_p^(c,2)(X, Y) = ( min_π Σ_{i=1}^m d^(c)(x_i, y_π(i))^p + (c^p / 2) (n − m) )^{1/p}
                    = ( min_γ [ Σ_{(i,j)∈γ} d(x_i, y_j)^p
                                + (c^p/2) (|X| − |γ|) + (c^p/2) (|Y| − |γ|) ] )^{1/p}

over partial assignments ``γ`` of pairs with ``d < c``: localisation + missed targets (truth
not assigned) + false targets (estimates not assigned).  An assigned pair at distance ``≥ c``
costs ``c^p``, the same as one missed plus one false target, and is counted as those.  Not
normalised by the cardinality (unlike OSPA); a metric.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from covnet.core.gaussian import Mat

__all__ = ["GospaResult", "gospa", "ospa"]

IntMat = NDArray[np.intp]


def _point_set(name: str, A: ArrayLike) -> Mat:
    a = np.asarray(A, dtype=np.float64)
    if a.size == 0:
        return np.zeros((0, a.shape[-1] if a.ndim == 2 else 0))
    if a.ndim != 2:
        raise ValueError(f"{name}: expected an (m, d) array of points, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite coordinates")
    return a


def _check(c: float, p: float) -> tuple[float, float]:
    cc, pp = float(c), float(p)
    if not (math.isfinite(cc) and cc > 0.0):
        raise ValueError(f"c: expected a finite cut-off > 0, got {c!r}")
    if not (math.isfinite(pp) and pp >= 1.0):
        raise ValueError(f"p: expected a finite order >= 1, got {p!r}")
    return cc, pp


def _sets(X: ArrayLike, Y: ArrayLike) -> tuple[Mat, Mat]:
    x, y = _point_set("X", X), _point_set("Y", Y)
    if x.shape[0] and y.shape[0] and x.shape[1] != y.shape[1]:
        raise ValueError(f"X, Y: points of different dimension ({x.shape[1]} and {y.shape[1]})")
    return x, y


def _distances(x: Mat, y: Mat) -> Mat:
    return np.asarray(np.linalg.norm(x[:, None, :] - y[None, :, :], axis=-1))


def ospa(X: ArrayLike, Y: ArrayLike, c: float, p: float = 2.0) -> float:
    """The OSPA distance of the module docstring (``0 ≤ OSPA ≤ c``)."""
    cc, pp = _check(c, p)
    x, y = _sets(X, Y)
    if x.shape[0] > y.shape[0]:
        x, y = y, x
    m, n = x.shape[0], y.shape[0]
    if n == 0:
        return 0.0
    if m == 0:
        return cc
    cost = np.minimum(_distances(x, y), cc) ** pp
    r, k = linear_sum_assignment(cost)
    total = float(cost[r, k].sum()) + cc**pp * (n - m)
    return float((total / n) ** (1.0 / pp))


@dataclass(frozen=True, slots=True)
class GospaResult:
    """GOSPA (``α = 2``) and its decomposition: ``distance = (localisation + missed +
    false)^(1/p)``; ``localisation = Σ d(x_i, y_j)^p`` over the assigned ``pairs`` ``(k, 2)``
    (rows ``(i into X, j into Y)``, all with ``d < c``); ``missed = (c^p/2) n_missed``,
    ``false = (c^p/2) n_false``."""

    distance: float
    localisation: float
    missed: float
    false: float
    n_missed: int
    n_false: int
    pairs: IntMat


def gospa(X: ArrayLike, Y: ArrayLike, c: float, p: float = 2.0) -> GospaResult:
    """The GOSPA distance (``α = 2``) of truth ``X`` and estimates ``Y``, with its
    localisation / missed / false decomposition (module docstring)."""
    cc, pp = _check(c, p)
    x, y = _sets(X, Y)
    m, n = x.shape[0], y.shape[0]
    half = 0.5 * cc**pp
    if m == 0 or n == 0:
        pairs = np.zeros((0, 2), dtype=np.intp)
        missed, false = half * m, half * n
        return GospaResult(float((missed + false) ** (1.0 / pp)), 0.0, missed, false, m, n, pairs)
    D = _distances(x, y)
    cost = np.minimum(D, cc) ** pp
    r, k = linear_sum_assignment(cost)
    keep = D[r, k] < cc
    r, k = r[keep], k[keep]
    localisation = float((D[r, k] ** pp).sum())
    n_missed, n_false = m - r.size, n - r.size
    missed, false = half * n_missed, half * n_false
    pairs = np.stack([r, k], axis=1).astype(np.intp)
    distance = float((localisation + missed + false) ** (1.0 / pp))
    return GospaResult(distance, localisation, missed, false, n_missed, n_false, pairs)
