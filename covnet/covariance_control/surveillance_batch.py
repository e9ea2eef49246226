"""Batches of surveillance runs: ``covnet mc`` (seeds) and ``covnet sweep`` over the search
weight λ (``sweep.search_weight``), each seed one in-process run through the engine in a worker
of the batch layer (:mod:`covnet.batches.trials`: on the local cores, written to ``OUT/trials``
as it finishes, the same command resumes).

Per seed and metric (:func:`seed_row`): the scalars of the run's summary
(:func:`~covnet.covariance_control.surveillance_results.surveillance_summary`) with
``rmse_tracked`` (``√(Σ localisation / Σ pairs)`` over the scans: the position RMSE of the
confirmed tracks that hold a target) and ``track_value`` (the mean over scans of the tracks'
``Σ_t w_t f(P_t, P_d,t)``: the covariance-control term the search competes with), and per scan
the GOSPA, its missed part and the cardinality.  Aggregates: per scalar the mean over seeds,
its 95 % Student interval, the median, min and max (``covnet.batches.stats.interval``);
per scan the mean and its interval.

The sweep (:func:`weight_sweep`): every ``λ`` of the grid with the same seeds; its table and
figure read the trade-off: time to confirm and the missed-target part of GOSPA (what search
buys) against the tracked targets' ``f`` and RMSE (what it costs).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from covnet.batches.stats import (
    NONNEGATIVE,
    SHARE,
    interval,
    interval_text,
    per_scan_interval,
)
from covnet.batches.trials import Batch, BatchProgress, Outcome, run_trials, trial_hash
from covnet.covariance_control.config import Scenario, from_dict, normalised
from covnet.runs.rundir import save_figure

__all__ = [
    "SCALARS",
    "aggregate",
    "compare_figure",
    "format_table",
    "paired",
    "policy_compare",
    "seed_row",
    "sweep_figure",
    "weight_sweep",
]

#: the per-seed scalars (summary keys and the two derived ones)
SCALARS = (
    "gospa_mean", "gospa_missed", "gospa_false", "gospa_localisation", "ospa_mean",
    "cardinality_error_mean", "time_to_confirm_mean", "missed_targets", "track_breaks",
    "id_switches", "false_tracks", "search_share", "rmse_tracked", "track_value",
)  # fmt: skip


def seed_row(data: Mapping[str, Any], seed: int) -> dict[str, Any]:
    """One seed (a worker's task; top level so it pickles): every metric's run, summarised."""
    # start-up: the workers import what the config needs
    from covnet.covariance_control import drive, surveillance
    from covnet.covariance_control.surveillance_results import surveillance_summary

    sc = from_dict({**data, "seed": seed}, f"seed {seed}")
    sm = surveillance.build(sc)
    out: dict[str, Any] = {"seed": seed, "surveillance": True, "metrics": {},
                           "decision_time_s": {}}  # fmt: skip
    for m in sc.allocation.metrics:
        r = drive.run(sc, m, sm).run
        out["decision_time_s"][m] = float(np.median(r.decision_s))
        s = surveillance_summary(r, sm.truth_ids)
        pairs = sum(len(p) for p in r.pairs)
        row = {k: s[k] for k in SCALARS if k in s}
        row["rmse_tracked"] = math.sqrt(float(r.gospa_loc.sum()) / pairs) if pairs else None
        row["track_value"] = float(np.mean(r.track_value)) if r.track_value.size else None
        row["gospa"] = r.gospa.tolist()
        row["gospa_missed_per_scan"] = r.gospa_missed.tolist()
        row["n_confirmed"] = r.n_confirmed.tolist()
        row["n_truth"] = r.n_truth.tolist()
        out["metrics"][m] = row
    return out


def _seeds(task: tuple[Mapping[str, Any], list[int]]) -> list[dict[str, Any]]:
    data, seeds = task
    return [seed_row(data, s) for s in seeds]


def aggregate(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Per metric: every scalar's :func:`interval` over the seeds; per scan the GOSPA and the
    confirmed tracks with their intervals (module docstring)."""
    out: dict[str, Any] = {}
    for m in rows[0]["metrics"]:
        per = [r["metrics"][m] for r in rows]
        # every scalar and curve here is >= 0 (a distance, a count, a share)
        blk: dict[str, Any] = {
            k: interval(
                [p.get(k) for p in per], bounds=SHARE if k == "search_share" else NONNEGATIVE
            )
            for k in SCALARS
        }
        blk["gospa_per_scan"] = per_scan_interval([p["gospa"] for p in per], bounds=NONNEGATIVE)
        blk["n_confirmed_per_scan"] = per_scan_interval(
            [p["n_confirmed"] for p in per], bounds=NONNEGATIVE
        )
        out[m] = blk
    return out


def _ci(b: Mapping[str, Any], fmt: str = "{:.2f}") -> str:
    return interval_text(b, fmt)


def format_table(agg: Mapping[str, Any], n_seeds: int) -> str:
    """The headline numbers of :func:`aggregate`, means with their 95 % intervals."""
    lines = [f"{n_seeds} seeds, means with 95 % confidence intervals"]
    for m, b in agg.items():
        lines.append(
            f"  {m}: GOSPA {_ci(b['gospa_mean'], '{:.1f}')} m, time to confirm "
            f"{_ci(b['time_to_confirm_mean'], '{:.1f}')} scans, missed targets "
            f"{_ci(b['missed_targets'])}, false tracks {_ci(b['false_tracks'])}, breaks "
            f"{_ci(b['track_breaks'])}, search share {_ci(b['search_share'], '{:.3f}')}, "
            f"tracked RMSE {_ci(b['rmse_tracked'], '{:.1f}')} m"
        )
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# the sweep over the search weight


def _point(weight: float) -> str:
    return f"search.weight={weight:g}"


def _run_points(
    command: str,
    sc: Scenario,
    datas: Mapping[str, dict[str, Any]],
    n_seeds: int,
    out: Path | None,
    workers: int | None,
    progress: BatchProgress | None,
) -> tuple[dict[str, list[dict[str, Any]]], Outcome]:
    """Every point's config (``datas``: point -> normalised config) over ``n_seeds`` seeds
    from the config's, on the batch layer; per point one row per metric with the aggregate's
    intervals (``seeds``: how many ran)."""

    def task(point: str, seeds: list[int]) -> tuple[dict[str, Any], list[int]]:
        return datas[point], seeds

    key = None
    if out is not None:
        base = {k: v for k, v in normalised(sc).items() if k != "seed"}
        key = trial_hash(command, {"kind": "surveillance", "config": base, "points": datas})
    b = Batch(command, _seeds, task, list(datas), first_seed=sc.seed)
    outcome = run_trials(b, n_seeds, out=out, key=key, workers=workers, progress=progress)
    rows = {
        p: [{"metric": m, "seeds": outcome.seeds[p], **{k: blk[k] for k in SCALARS}}
            for m, blk in aggregate(outcome.results[p]).items()]
        for p in datas
    }  # fmt: skip
    return rows, outcome


def weight_sweep(
    sc: Scenario,
    weights: Sequence[float],
    n_seeds: int,
    *,
    out: Path | None = None,
    workers: int | None = None,
    progress: BatchProgress | None = None,
) -> tuple[list[dict[str, Any]], Outcome]:
    """Every weight of ``weights`` over ``n_seeds`` seeds from the config's: one row per
    weight and metric with the aggregate's intervals (module docstring)."""
    data = normalised(sc)
    datas: dict[str, dict[str, Any]] = {}
    for w in weights:
        surv = {**data["surveillance"], "search": {**data["surveillance"]["search"], "weight": w}}
        datas[_point(w)] = {**data, "surveillance": surv}
    by_point, outcome = _run_points("sweep", sc, datas, n_seeds, out, workers, progress)
    rows = [
        {"search_weight": w, **r} for w in weights for r in by_point[_point(w)]
    ]  # fmt: skip
    return rows, outcome


def sweep_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The sweep's rows: per weight and metric the trade-off's numbers with their intervals."""
    lines = ["λ (search.weight) | metric | time to confirm | GOSPA missed part | tracked f | "
             "tracked RMSE (m) | search share"]  # fmt: skip
    for r in rows:
        lines.append(
            f"{r['search_weight']:g} | {r['metric']} | {_ci(r['time_to_confirm_mean'], '{:.1f}')}"
            f" | {_ci(r['gospa_missed'], '{:.0f}')} | {_ci(r['track_value'], '{:.3g}')} | "
            f"{_ci(r['rmse_tracked'], '{:.1f}')} | {_ci(r['search_share'], '{:.2f}')}"
        )
    return "\n".join(lines)


def sweep_figure(out: Path, rows: Sequence[Mapping[str, Any]]) -> Path:
    """``sweep.png``: against λ, the time to confirm and the missed-target GOSPA part (left),
    the tracked targets' f and RMSE (right), each mean with its 95 % interval."""
    # start-up: matplotlib only for the figure
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(10, 7), layout="constrained")
    panels = [("time_to_confirm_mean", "time to confirm (scans)"),
              ("gospa_missed", "GOSPA missed part (m²)"),
              ("track_value", "tracked targets' Σ w f"),
              ("rmse_tracked", "tracked position RMSE (m)")]  # fmt: skip
    for ax, (key, label) in zip(axes.ravel(), panels, strict=True):
        for m in sorted({str(r["metric"]) for r in rows}):
            rr = [r for r in rows if r["metric"] == m and r[key]["mean"] is not None]
            x = np.array([r["search_weight"] for r in rr])
            y = np.array([r[key]["mean"] for r in rr])
            lo = np.array([(r[key]["ci95"] or [r[key]["mean"]] * 2)[0] for r in rr])
            hi = np.array([(r[key]["ci95"] or [r[key]["mean"]] * 2)[1] for r in rr])
            ax.errorbar(x, y, yerr=[y - lo, hi - y], marker="o", capsize=3, label=m)
        ax.set_xscale("symlog", linthresh=1.0)  # λ = 0 and decades of λ on one axis
        ax.set_xlabel("search weight λ")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    n = rows[0]["seeds"] if rows else 0
    return _save(fig, axes, f"Search against track: means over {n} seeds with 95 % intervals",
                 out / "sweep.png")  # fmt: skip


def _save(fig: Any, axes: Any, title: str, path: Path) -> Path:
    """A batch figure's legend (first panel), title, file; the figure closed."""
    import matplotlib.pyplot as plt  # start-up: matplotlib only for the figures

    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title)
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------------
# the policies side by side


def policy_compare(
    sc: Scenario,
    policies: Sequence[str],
    budget: int | None,
    n_seeds: int,
    *,
    out: Path | None = None,
    workers: int | None = None,
    progress: BatchProgress | None = None,
) -> tuple[list[dict[str, Any]], Outcome]:
    """``covnet compare --policies`` of a surveillance config: every policy (its many-target
    form on the tracks, the sensors it leaves off searching:
    :meth:`~covnet.covariance_control.surveillance_centre.SurveillanceCentre._by_policy`) on
    the same ``n_seeds`` seeds (paired), one row per policy and metric with the scalars'
    intervals; with covariance control among them, each other row also holds its paired
    differences from it (:func:`paired`)."""
    # start-up: the policies' scenario rules
    from covnet.covariance_control import compare_policies as cp

    datas: dict[str, dict[str, Any]] = {}
    for p in policies:
        k = cp.budget_for(sc, p, budget)
        datas[cp.point_of(p, k)] = normalised(cp.scenario_for(sc, p, k))
    by_point, outcome = _run_points("compare", sc, datas, n_seeds, out, workers, progress)
    rows = [{"point": p, **r} for p, rs in by_point.items() for r in rs]
    if cp.REFERENCE in policies:
        ref = cp.point_of(cp.REFERENCE, cp.budget_for(sc, cp.REFERENCE, budget))
        for r in rows:
            if r["point"] != ref:
                paired(r, outcome.results[r["point"]], outcome.results[ref], cp.REFERENCE)
    return rows, outcome


def paired(
    row: dict[str, Any],
    seeds: Sequence[Mapping[str, Any]],
    ref: Sequence[Mapping[str, Any]],
    reference: str,
) -> None:
    """Add to one policy's ``row`` (one metric) its paired differences from ``reference``'s
    runs over the seeds both ran: per seed ``d_s = x_s(policy) - x_s(reference)`` of every
    scalar of :data:`SCALARS` (the same seed: the same targets, clutter and noise), and their
    :func:`interval` (``<scalar>_vs_reference``: mean, Student 95 % interval, not cut: a
    difference may have either sign).  A seed where either side has no value (no target ever
    confirmed: no time to confirm) is left out of that scalar's difference.  Paired, a
    difference is shown when its interval excludes 0, which two overlapping intervals of the
    rows do not decide either way."""
    m = row["metric"]
    by_seed = {int(s["seed"]): s["metrics"][m] for s in ref if m in s["metrics"]}
    common = [(s["metrics"][m], by_seed[int(s["seed"])]) for s in seeds
              if int(s["seed"]) in by_seed and m in s["metrics"]]  # fmt: skip
    if not common:
        return
    row["vs_reference"] = reference
    for k in SCALARS:
        d = [None if a.get(k) is None or b.get(k) is None else float(a[k]) - float(b[k])
             for a, b in common]  # fmt: skip
        row[f"{k}_vs_reference"] = interval(d)


def compare_figure(out: Path, rows: Sequence[Mapping[str, Any]]) -> Path:
    """``compare.png``: per policy (and metric), GOSPA, the time to confirm, the false tracks
    and the tracked targets' RMSE, each mean with its 95 % interval over the paired seeds."""
    # start-up: matplotlib only for the figure
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = list(dict.fromkeys(str(r["point"]) for r in rows))
    metrics = sorted({str(r["metric"]) for r in rows})
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), layout="constrained")
    panels = [("gospa_mean", "GOSPA (m)"),
              ("time_to_confirm_mean", "time to confirm (scans)"),
              ("false_tracks", "false tracks"),
              ("rmse_tracked", "tracked position RMSE (m)")]  # fmt: skip
    width = 0.8 / max(len(metrics), 1)
    for ax, (key, label) in zip(axes.ravel(), panels, strict=True):
        for i, m in enumerate(metrics):
            x, y, lo, hi = [], [], [], []
            for j, p in enumerate(points):
                r = next((r for r in rows if r["point"] == p and r["metric"] == m), None)
                if r is None or r[key]["mean"] is None:
                    continue
                mean = float(r[key]["mean"])
                ci = r[key]["ci95"] or [mean, mean]
                x.append(j + (i - (len(metrics) - 1) / 2) * width)
                y.append(mean)
                lo.append(mean - float(ci[0]))
                hi.append(float(ci[1]) - mean)
            ax.errorbar(x, y, yerr=[lo, hi], fmt="o", capsize=3, label=m)
        ax.set_xticks(range(len(points)))
        ax.set_xticklabels([p.replace("policy=", "").replace(",", "\n") for p in points],
                           fontsize=7)  # fmt: skip
        ax.set_ylabel(label)
        ax.set_ylim(bottom=0.0)  # all four are >= 0
        ax.grid(alpha=0.3, axis="y")
    n = rows[0]["seeds"] if rows else 0
    title = f"Policies side by side: means over the same {n} seeds with 95 % intervals"
    return _save(fig, axes, title, out / "compare.png")


def compare_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The policies' rows: means with their 95 % intervals; then each policy's paired
    differences from the reference (:func:`paired`), where they were computed."""
    lines = ["policy | metric | GOSPA (m) | time to confirm | missed targets | false tracks | "
             "breaks | tracked RMSE (m) | search share"]  # fmt: skip
    for r in rows:
        lines.append(
            f"{r['point']} | {r['metric']} | {_ci(r['gospa_mean'], '{:.1f}')} | "
            f"{_ci(r['time_to_confirm_mean'], '{:.1f}')} | {_ci(r['missed_targets'])} | "
            f"{_ci(r['false_tracks'], '{:.1f}')} | {_ci(r['track_breaks'], '{:.1f}')} | "
            f"{_ci(r['rmse_tracked'], '{:.1f}')} | {_ci(r['search_share'], '{:.2f}')}"
        )
    versus = [r for r in rows if r.get("vs_reference")]
    if versus:
        lines.append(
            f"paired against {versus[0]['vs_reference']} (the same seeds, the same metric: mean "
            "difference and its 95 % t interval; '=' where the interval contains 0: no "
            "difference shown):"
        )
        for r in versus:
            lines.append(
                f"{r['point']} | {r['metric']} | GOSPA "
                f"{_signed(r['gospa_mean_vs_reference'], '{:+.1f}')} m, time to confirm "
                f"{_signed(r['time_to_confirm_mean_vs_reference'], '{:+.1f}')} scans, missed "
                f"targets {_signed(r['missed_targets_vs_reference'])}, false tracks "
                f"{_signed(r['false_tracks_vs_reference'], '{:+.1f}')}, tracked RMSE "
                f"{_signed(r['rmse_tracked_vs_reference'], '{:+.1f}')} m"
            )
    return "\n".join(lines)


def _signed(b: Mapping[str, Any], fmt: str = "{:+.2f}") -> str:
    """A paired difference's mean and interval, ``=`` appended where the interval holds 0."""
    return interval_text(b, fmt, zero_mark=True)
