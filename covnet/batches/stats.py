"""Statistics over seeds, the same for every batch command (``covnet sweep``, ``compare``,
``mc``): the mean, the sample standard deviation and the 95 % confidence interval of the mean
(Student t with ``n - 1`` degrees of freedom: seeds are independent replications, a run's scans
are not), and per-scan curves with their bands.

With one seed there is no spread: the standard deviation and the interval are ``None``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = [
    "CI_LEVEL",
    "CUT",
    "UNBOUNDED",
    "Bounds",
    "NONNEGATIVE",
    "SHARE",
    "add_stats",
    "ci_half_width",
    "count_range",
    "curves_of",
    "error_stats",
    "median",
    "per_scan_bands",
    "plus_minus",
    "seed_stats",
    "t_half_width",
    "t_quantile",
]

CI_LEVEL = 0.95


def median(values: Any) -> float:
    """The median of ``values`` as :func:`numpy.median` computes it, bit for bit (the middle
    element, or ``(a + b) / 2`` of the two middle ones; NaN if any is NaN), without its import
    of ``numpy.ma`` (start-up time of ``covnet run``, whose summaries report medians)."""
    s = np.sort(np.asarray(values, dtype=np.float64).ravel())
    n = s.size
    if n == 0 or np.isnan(s[-1]):
        return math.nan
    mid = n // 2
    return float(s[mid]) if n % 2 else float((s[mid - 1] + s[mid]) / 2)


def t_quantile(dof: int, level: float = CI_LEVEL) -> float:
    """The two-sided Student t quantile ``t_{(1 + level) / 2}(dof)``."""
    from scipy.stats import t as student_t  # scipy.stats: only the tables need it (start-up)

    return float(student_t.ppf(0.5 + level / 2.0, dof))


def t_half_width(std: Any, n: int, level: float = CI_LEVEL) -> Any:
    """Half the width of the Student t interval (``level``) of the mean of ``n`` >= 2
    independent values of sample standard deviation ``std`` (ddof 1): ``t_{(1 + level) / 2}(n -
    1) · std / √n``; ``std`` a float or an array (one interval per element).  Every t interval
    of covnet is this one."""
    return t_quantile(n - 1, level) * std / math.sqrt(n)


Bounds = tuple[float | None, float | None]
"""The range a quantity lives in, ``(lo, hi)`` (None: unbounded on that side)."""
UNBOUNDED: Bounds = (None, None)
NONNEGATIVE: Bounds = (0.0, None)
"""A distance, a count, an RMSE, a NEES: ``>= 0``."""
SHARE: Bounds = (0.0, 1.0)
"""A rate or a share: within ``[0, 1]``."""


def seed_stats(values: Iterable[float], bounds: Bounds = UNBOUNDED) -> dict[str, Any]:
    """``{"n", "mean", "std", "ci_lo", "ci_hi"}`` of independent per-seed values: ``std`` the
    sample standard deviation (ddof 1), ``[ci_lo, ci_hi]`` the 95 % Student t interval of the
    mean, cut to the quantity's ``bounds`` (a few seeds' interval of an RMSE reached -54 m, of
    a miss rate 1.02: the interval of the mean intersected with the range the mean lies in,
    as :func:`interval` and :func:`per_scan_bands` clip theirs); ``None`` where undefined (one
    value; NaN values are left out)."""
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    v = v[np.isfinite(v)]
    n = int(v.size)
    if n == 0:
        return {"n": 0, "mean": None, "std": None, "ci_lo": None, "ci_hi": None}
    mean = float(v.mean())
    if n < 2:
        return {"n": 1, "mean": mean, "std": None, "ci_lo": None, "ci_hi": None}
    std = float(v.std(ddof=1))
    half = t_half_width(std, n)
    ci_lo, ci_hi = _within(mean - half, mean + half, bounds)
    return {"n": n, "mean": mean, "std": std, "ci_lo": ci_lo, "ci_hi": ci_hi}


def _within(lo: float, hi: float, bounds: Bounds) -> tuple[float, float]:
    """The interval ``[lo, hi]`` cut to ``bounds``."""
    floor, ceiling = bounds
    return (lo if floor is None else max(lo, floor), hi if ceiling is None else min(hi, ceiling))


CUT = "[lo, hi] where the interval is cut at the quantity's range"
"""How a table's legend says what :func:`plus_minus` prints for a cut interval."""


def plus_minus(
    mean: float, lo: float | None, hi: float | None, spec: str = ".2f", sep: str = " ± "
) -> str:
    """``mean ± half-width`` of an interval, or ``mean [lo, hi]`` when the interval is not
    centred on the mean (cut by the quantity's bounds: :func:`seed_stats`), ``mean`` alone
    without one."""
    if lo is None or hi is None:
        return format(mean, spec)
    below, above = mean - lo, hi - mean
    if abs(below - above) <= 1e-9 * max(abs(below), abs(above), abs(mean), 1e-300):
        return f"{format(mean, spec)}{sep}{format((hi - lo) / 2, spec)}"
    return f"{format(mean, spec)} [{format(lo, spec)}, {format(hi, spec)}]"


def interval_text(b: Mapping[str, Any], fmt: str = "{:.2f}", *, zero_mark: bool = False) -> str:
    """An :func:`interval` summary as a table says it: ``mean [lo, hi]``, the mean alone
    without an interval (one value), ``-`` without a value; ``zero_mark``: ``" ="`` appended
    where the interval holds 0 (a paired difference not shown by these seeds)."""
    if b["mean"] is None:
        return "-"
    if b["ci95"] is None:
        return fmt.format(b["mean"])
    lo, hi = b["ci95"]
    same = " =" if zero_mark and lo <= 0.0 <= hi else ""
    return f"{fmt.format(b['mean'])} [{fmt.format(lo)}, {fmt.format(hi)}]{same}"


def count_range(counts: Iterable[int]) -> str:
    """Seed counts as a title says them: ``"6"``, or ``"6-9"`` where ``--ci-width`` gave the
    points different counts."""
    c = sorted({int(n) for n in counts})
    if not c:
        return "0"
    return str(c[0]) if len(c) == 1 else f"{c[0]}-{c[-1]}"


def ci_half_width(stats: Mapping[str, Any]) -> float:
    """Half the width of a :func:`seed_stats` interval (infinite when there is none)."""
    if stats.get("ci_lo") is None or stats.get("ci_hi") is None:
        return math.inf
    return 0.5 * (float(stats["ci_hi"]) - float(stats["ci_lo"]))


def add_stats(
    row: dict[str, Any], name: str, values: Iterable[float], bounds: Bounds = UNBOUNDED
) -> dict[str, Any]:
    """Add ``<name>_mean``, ``<name>_std``, ``<name>_ci_lo`` and ``<name>_ci_hi`` (the
    :func:`seed_stats` of ``values`` within ``bounds``) to ``row``; returns the stats."""
    s = seed_stats(values, bounds)
    for k in ("mean", "std", "ci_lo", "ci_hi"):
        row[f"{name}_{k}"] = s[k]
    return s


def per_scan_bands(err2: np.ndarray, nees: np.ndarray, state_dim: int = 4) -> dict[str, np.ndarray]:
    """Per-scan curves over ``R`` seeds from ``err2`` and ``nees`` ``(R, N)``: the RMSE
    ``sqrt(mean_s e²_{s,k})`` with the square roots of the t interval of the mean squared error
    (``rmse_lo``, ``rmse_hi``; the lower end clipped at 0); the mean NEES with its t interval
    (``nees_lo``, ``nees_hi``) and the 95 % chi-square band of a consistent filter's R-seed
    average (``nees_band``: ``[lo, hi]``, the same at every scan)."""
    from scipy.stats import chi2  # scipy.stats: only the tables need it (start-up)

    err2 = np.asarray(err2, dtype=np.float64)
    nees = np.asarray(nees, dtype=np.float64)
    R = err2.shape[0]
    out: dict[str, np.ndarray] = {}
    mse = err2.mean(axis=0)
    mn = nees.mean(axis=0)
    if R >= 2:
        h_mse = t_half_width(err2.std(axis=0, ddof=1), R)
        h_nees = t_half_width(nees.std(axis=0, ddof=1), R)
    else:
        h_mse = np.full_like(mse, np.nan)
        h_nees = np.full_like(mn, np.nan)
    out["rmse"] = np.sqrt(mse)
    out["rmse_lo"] = np.sqrt(np.clip(mse - h_mse, 0.0, None))
    out["rmse_hi"] = np.sqrt(mse + h_mse)
    out["nees"] = mn
    out["nees_lo"] = mn - h_nees
    out["nees_hi"] = mn + h_nees
    out["nees_band"] = np.asarray(chi2.ppf([0.025, 0.975], state_dim * R)) / R
    return out


def burn_in_of(burn_in: int, scans: int) -> int:
    """The burn-in used for runs of ``scans`` scans: ``burn_in``, at most half the run (a short
    run keeps its second half)."""
    return max(0, min(burn_in, scans // 2))


def error_stats(
    row: dict[str, Any], err2: np.ndarray, nees: np.ndarray, burn_in: int
) -> dict[str, Any]:
    """Add to ``row`` the error statistics over ``R`` seeds of per-scan squared position errors
    ``err2`` and NEES ``nees`` ``(R, N)``, with the first ``b`` = :func:`burn_in_of` scans the
    transient:

    - ``burn_in_scans`` (``b``);
    - ``rmse_position_mean/std/ci_lo/ci_hi``: of the per-seed RMSE over the whole run;
    - ``rmse_steady``: the root of the mean over seeds of the per-seed mean squared error after
      the burn-in (as ``rmse_position`` is over the whole run), and the statistics of the
      per-seed RMSE after it (``rmse_steady_mean`` ...): the headline;
    - ``rmse_transient`` (the same over the first ``b`` scans; None when ``b`` is 0),
      its statistics and ``rmse_transient_max`` (the worst seed's);
    - ``nees_steady_mean/std/ci_lo/ci_hi``: of the per-seed mean NEES after the burn-in.
    """
    err2 = np.asarray(err2, dtype=np.float64)
    nees = np.asarray(nees, dtype=np.float64)
    b = burn_in_of(burn_in, err2.shape[1])
    row["burn_in_scans"] = b
    add_stats(row, "rmse_position", np.sqrt(err2.mean(axis=1)), NONNEGATIVE)
    steady = err2[:, b:].mean(axis=1)
    row["rmse_steady"] = float(np.sqrt(steady.mean()))
    add_stats(row, "rmse_steady", np.sqrt(steady), NONNEGATIVE)
    if b:
        transient = err2[:, :b].mean(axis=1)
        row["rmse_transient"] = float(np.sqrt(transient.mean()))
        add_stats(row, "rmse_transient", np.sqrt(transient), NONNEGATIVE)
        row["rmse_transient_max"] = float(np.sqrt(transient.max()))
    else:
        row["rmse_transient"] = row["rmse_transient_max"] = None
        add_stats(row, "rmse_transient", [])
    add_stats(row, "nees_steady", nees[:, b:].mean(axis=1), NONNEGATIVE)
    return row


def curves_of(results: Mapping[str, Sequence[Mapping[str, Any]]]) -> dict[str, np.ndarray]:
    """The per-scan curves (:func:`per_scan_bands`) of every point of a batch's ``results``
    (point key -> its runs, each with ``pos_err2_scan`` and ``nees_scan``), stacked
    ``(points, scans)``, with ``points`` (their keys) and ``seeds`` (per point)."""
    keys = [k for k, rs in results.items() if rs]
    bands = [
        per_scan_bands(
            np.asarray([r["pos_err2_scan"] for r in results[k]], dtype=np.float64),
            np.asarray([r["nees_scan"] for r in results[k]], dtype=np.float64),
        )
        for k in keys
    ]
    out = {name: np.stack([b[name] for b in bands]) for name in (bands[0] if bands else {})}
    out["points"] = np.asarray(keys, dtype=str)
    out["seeds"] = np.asarray([len(results[k]) for k in keys], dtype=np.int64)
    return out


def interval(values: Sequence[float | None], *, bounds: Bounds = UNBOUNDED) -> dict[str, Any]:
    """Mean, standard deviation (ddof 1), the 95 % confidence interval of the mean (Student's
    t; ``None`` for one value), median, min, max and how many values (``None`` ones are left
    out): every Monte Carlo scalar's summary over seeds.  ``bounds``: the quantity's range, to
    which the interval is cut, as :func:`seed_stats` cuts its own (:data:`NONNEGATIVE`: a
    distance, a count, a NEES, whose few seeds' Student interval reached below 0, a tracked
    RMSE of 14.6 [-6.6, 35.7] m with two seeds; :data:`SHARE`: a rate)."""
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    if v.size == 0:
        return {
            "mean": None,
            "std": None,
            "ci95": None,
            "median": None,
            "min": None,
            "max": None,
            "n": 0,
        }
    mean = float(v.mean())
    if v.size < 2:
        return {
            "mean": mean,
            "std": None,
            "ci95": None,
            "median": mean,
            "min": mean,
            "max": mean,
            "n": 1,
        }
    sd = float(v.std(ddof=1))
    half = float(t_half_width(sd, v.size))
    return {
        "mean": mean,
        "std": sd,
        "ci95": list(_within(mean - half, mean + half, bounds)),
        "median": float(np.median(v)),
        "min": float(v.min()),
        "max": float(v.max()),
        "n": int(v.size),
    }


def per_scan_interval(
    rows: Sequence[Sequence[float]], *, bounds: Bounds = UNBOUNDED
) -> dict[str, list[float] | None]:
    """Per scan (``rows``: one series per seed): the mean over seeds and its 95 % interval
    (cut to ``bounds``, as :func:`interval`'s; ``None`` with one seed, as :func:`interval`'s:
    it gave the mean as both ends, an interval of zero width)."""
    a = np.asarray(rows, dtype=np.float64)
    mean = a.mean(axis=0)
    if a.shape[0] < 2:
        return {"mean": mean.tolist(), "ci95_low": None, "ci95_high": None}
    half = t_half_width(a.std(axis=0, ddof=1), a.shape[0])
    floor, ceiling = bounds
    low, high = mean - half, mean + half
    return {
        "mean": mean.tolist(),
        "ci95_low": (low if floor is None else np.maximum(low, floor)).tolist(),
        "ci95_high": (high if ceiling is None else np.minimum(high, ceiling)).tolist(),
    }
