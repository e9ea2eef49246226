"""``covnet sweep CONFIG``: how sensor management and fusion degrade with delay and loss.

The grid is the config's ``sweep`` section (:class:`covnet.config.SweepSpec`): every
combination of mean one-way delay, loss probability, fusion mode, ``account_for_loss`` and late
policy, each over ``seeds`` seeds.  A grid point sets ``network.latency.uplink`` and
``downlink`` of every sensor (the config's per-sensor overrides are not used) and runs
:func:`covnet.covariance_control.latency_sim.run_latency` (application-level emulation in simulated
time: exact and deterministic, so a point with zero delay and zero loss *is* the plain run).  Per
point, averaged over the seeds:

- ``rmse_position`` (m), ``mean_nees`` (scans after the first 10), ``allocation_rate``;
- ``deadline_miss_rate``: the fraction of scans where something sent for the scan was not
  fused by its deadline;
- per run: ``late`` (arrived after their deadline: ``late_refiltered`` + ``late_dropped``; the
  policy itself is the point's ``late_policy``),
  ``lost`` (never arrived), ``commands_missed``, ``fused`` (measurements or tracks fused, on
  time or re-filtered) and ``measured``.

Then the statistics over seeds (:func:`covnet.batches.stats.error_stats`): the RMSE after
``evaluation.burn_in_scans`` (``rmse_steady``, the headline) and of the burn-in scans
(``rmse_transient``), each with its mean, standard deviation and 95 % Student t interval over
the per-seed values, and the same for the NEES after the burn-in and the allocation rate.

The runs are trials of the batch layer (:mod:`covnet.batches.trials`): on the local process pool or
a
Dask cluster, each written to ``OUT/trials`` as it finishes (the same command resumes), more
seeds for the wide points with ``--ci-width``; ``sweep.csv``, ``sweep.json``, ``curves.npz``
(per-scan RMSE and NEES with their bands, every point), ``sweep.png`` and ``curves.png`` are
written to the output directory.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from covnet.batches import point_text
from covnet.batches.pool import BatchInterrupted, write_rows
from covnet.batches.stats import (
    CUT,
    NONNEGATIVE,
    SHARE,
    add_stats,
    ci_half_width,
    count_range,
    curves_of,
    error_stats,
    plus_minus,
    seed_stats,
)
from covnet.batches.trials import (
    Batch,
    BatchProgress,
    Outcome,
    complete_points,
    point_key,
    run_trials,
    trial_hash,
)
from covnet.config import ConfigError
from covnet.covariance_control.config import Scenario, SweepSpec, from_dict, normalised
from covnet.covariance_control.latency_sim import run_latency
from covnet.covariance_control.model import build_model, truth_trajectory
from covnet.runs.rundir import save_figure

POINT_KEYS = ("delay_ms", "loss", "mode", "account_for_loss", "late_policy")
MEANS = (
    "mean_nees",
    "allocation_rate",
    "deadline_miss_rate",
    "late",
    "late_refiltered",
    "late_dropped",
    "lost",
    "commands_missed",
    "measured",
    "fused",
)
"""The per-run numbers a row averages over its seeds."""
SPREAD = {
    "allocation_rate": SHARE,
    "deadline_miss_rate": SHARE,
    "late": NONNEGATIVE,
    "lost": NONNEGATIVE,
}
"""The per-run numbers whose spread over seeds a row gives (``<name>_mean/std/ci_lo/ci_hi``,
:func:`covnet.batches.stats.add_stats`): every quantity the figure draws besides the errors'."""
STATS = (
    "burn_in_scans",
    "rmse_steady",
    "rmse_steady_mean",
    "rmse_steady_std",
    "rmse_steady_ci_lo",
    "rmse_steady_ci_hi",
    "rmse_transient",
    "rmse_transient_mean",
    "rmse_transient_std",
    "rmse_transient_ci_lo",
    "rmse_transient_ci_hi",
    "rmse_transient_max",
    "rmse_position_mean",
    "rmse_position_std",
    "rmse_position_ci_lo",
    "rmse_position_ci_hi",
    "nees_steady_mean",
    "nees_steady_std",
    "nees_steady_ci_lo",
    "nees_steady_ci_hi",
    *(f"{k}_{s}" for k in SPREAD for s in ("std", "ci_lo", "ci_hi")),
)
"""The statistics over seeds (:func:`covnet.batches.stats.error_stats`, and
:data:`SPREAD`'s), after the means."""
COLUMNS = (*POINT_KEYS, "seeds", "rmse_position", *MEANS, *STATS, "point")


def link_for(delay_ms: float, kind: str, loss: float) -> dict[str, Any]:
    """The ``network.latency`` link of a grid point (the config's own form)."""
    mean = delay_ms / 1000.0
    if mean == 0.0:
        delay: dict[str, Any] = {"kind": "constant", "value_s": 0.0}
    elif kind == "constant":
        delay = {"kind": "constant", "value_s": mean}
    elif kind == "uniform":
        delay = {"kind": "uniform", "low_s": 0.0, "high_s": 2.0 * mean}
    else:
        delay = {"kind": "exponential", "mean_s": mean}
    return {"delay": delay, "jitter_s": 0.0, "loss": loss, "reorder": 0.0}


def point_scenario(sc: Scenario, point: dict[str, Any], seed: int) -> Scenario:
    """``sc`` at one grid point with ``seed``."""
    spec = sc.sweep or SweepSpec()
    data = normalised(sc)
    link = link_for(point["delay_ms"], spec.delay_kind, point["loss"])
    data["network"]["latency"] = {
        **data["network"]["latency"],
        "uplink": link,
        "downlink": link,
        "sensors": {},  # the point sets every sensor's links
        "late": point["late_policy"],
    }
    data["fusion"] = {**data["fusion"], "mode": point["mode"]}
    data["allocation"] = {**data["allocation"], "account_for_loss": point["account_for_loss"]}
    data["seed"] = seed
    data["sweep"] = None  # one run: the grid is the batch's (its other points are not checked)
    return from_dict(data, f"{sc.name} (sweep point)")


#: the ``sweep:`` key of each grid point's key
AXIS = {
    "delay_ms": "delay_ms",
    "loss": "loss",
    "mode": "modes",
    "account_for_loss": "account_for_loss",
    "late_policy": "late",
}


def check_notes(sc: Scenario) -> list[str]:
    """``covnet check``'s note on a valid config whose ``sweep:`` grid ``covnet sweep`` refuses
    (:func:`refused_point`): the config validates only an axis given other than its default
    (``covnet run`` of a config with a ``sweep:`` section of seeds alone must not stop), so a
    default grid that the policy or search refuses passed the check and was refused by the
    sweep itself.  Surveillance, many targets and peer configs: checked apart or refused by
    ``covnet sweep`` as a whole."""
    if sc.sweep is None or sc.surveillance is not None or sc.multitarget:
        return []
    if not sc.fusion.has_centre:
        return []
    why = refused_point(sc, grid(sc.sweep))
    return (
        []
        if why is None
        else [f"note: the config is valid; covnet sweep would refuse its grid: {why}"]
    )


def refused_point(sc: Scenario, points: Sequence[dict[str, Any]]) -> str | None:
    """Why grid points cannot run, in one line (``None``: every point can): their config
    (:func:`point_scenario`) refused, named by each axis value every point of which is refused
    (``mode=ci``: the key to change is ``sweep.modes``), else the first such point by all its
    values.  ``covnet sweep`` asks before any run: a refused point stopped the batch halfway,
    with exit 2 on one worker and a traceback (exit 1) on several."""
    bad: dict[int, ConfigError] = {}
    for i, p in enumerate(points):
        try:
            point_scenario(sc, p, sc.seed)
        except ConfigError as e:
            bad[i] = e
    if not bad:
        return None

    def why(i: int) -> str:
        return "; ".join(f"{path}: {msg}" for path, msg in bad[i].problems)

    given = set() if sc.sweep is None else sc.sweep.model_fields_set
    causes: list[str] = []
    for k in POINT_KEYS:
        for v in dict.fromkeys(point_text(q[k]) for q in points):
            with_it = [i for i, q in enumerate(points) if point_text(q[k]) == v]
            if len(with_it) == len(points) or not all(i in bad for i in with_it):
                continue
            change = (
                f"take {v} out of sweep.{AXIS[k]}"
                if AXIS[k] in given
                else f"give sweep.{AXIS[k]} without {v} (by default "
                f"{', '.join(point_text(x) for x in getattr(SweepSpec(), AXIS[k]))})"
            )
            causes.append(
                f"grid point {k}={v} cannot run ({len(with_it)} of the {len(points)} points): "
                f"{why(with_it[0])}: {change}"
            )
    if causes:
        return f"sweep: {'; '.join(causes)}; or change the config"
    first = min(bad)
    named = ", ".join(f"{k}={point_text(points[first][k])}" for k in POINT_KEYS)
    return (
        f"sweep: grid point {named} cannot run ({len(bad)} of the {len(points)} points): "
        f"{why(first)}: change the config or its sweep: section"
    )


def grid(spec: SweepSpec) -> list[dict[str, Any]]:
    """Every grid point, in a fixed order."""
    return [
        dict(zip(POINT_KEYS, values, strict=True))
        for values in itertools.product(
            spec.delay_ms, spec.loss, spec.modes, spec.account_for_loss, spec.late
        )
    ]


def run_point(task: tuple[dict[str, Any], dict[str, Any], int, str]) -> dict[str, Any]:
    """One run at one grid point: the table's numbers of the run and its per-scan squared
    position error and NEES (``pos_err2_scan``, ``nees_scan``: the per-scan curves and the
    burn-in statistics come from them)."""
    data, point, seed, metric = task
    sc = point_scenario(from_dict(data), point, seed)
    model = build_model(sc)
    run, counts = run_latency(sc, metric, model)
    err = run.x_est - truth_trajectory(model)
    e2 = err[:, 0] ** 2 + err[:, 2] ** 2
    c = counts.as_dict()
    return {
        **point,
        "seed": seed,
        "pos_err2": float(np.mean(e2)),
        "mean_nees": float(run.nees[10:].mean() if len(run.nees) > 10 else run.nees.mean()),
        "allocation_rate": float(run.enabled.mean()),
        "deadline_miss_rate": c["deadline_misses"] / len(run.value),
        "late": c["late_refiltered"] + c["late_dropped"],
        "fused": c["on_time"] + c["late_refiltered"],
        **{
            k: c[k]
            for k in ("late_refiltered", "late_dropped", "lost", "commands_missed", "measured")
        },
        "pos_err2_scan": e2.tolist(),
        "nees_scan": np.asarray(run.nees, dtype=np.float64).tolist(),
    }


def run_seeds(task: tuple[dict[str, Any], dict[str, Any], list[int], str]) -> list[dict[str, Any]]:
    """The runs of one grid point with each of ``seeds`` (a task of the batch layer,
    :mod:`covnet.batches.trials`: module level, so that local and cluster workers import it)."""
    data, point, seeds, metric = task
    return [run_point((data, point, seed, metric)) for seed in seeds]


def trial_key(sc: Scenario, metric: str) -> str:
    """The hash that keys the sweep's trials (:func:`covnet.batches.trials.trial_hash`): the config
    without its seed, its seed count and its evaluation settings (which change no run), and
    the metric."""
    data = normalised(sc)
    data.pop("seed", None)
    data.pop("evaluation", None)
    if data.get("sweep"):
        data["sweep"] = {k: v for k, v in data["sweep"].items() if k != "seeds"}
    return trial_hash("sweep", {"config": data, "metric": metric})


def batch(sc: Scenario, metric: str) -> tuple[Batch, dict[str, dict[str, Any]]]:
    """The sweep as a :class:`covnet.batches.trials.Batch` (headline: the steady-state RMSE), and
    its
    grid points by key."""
    spec = sc.sweep or SweepSpec()
    points = {point_key(p): p for p in grid(spec)}
    data = normalised(sc)
    burn = sc.evaluation.burn_in_scans

    def task(key: str, seeds: list[int]) -> Any:
        return (data, points[key], seeds, metric)

    def headline(key: str, runs: list[dict[str, Any]]) -> float:
        E = np.asarray([r["pos_err2_scan"] for r in runs], dtype=np.float64)
        b = min(burn, E.shape[1] // 2)
        return ci_half_width(seed_stats(np.sqrt(E[:, b:].mean(axis=1))))

    return (
        Batch(
            "sweep",
            run_seeds,
            task,
            list(points),
            first_seed=sc.seed,
            headline=headline,
            headline_name="steady-state RMSE (m)",
        ),
        points,
    )


def sweep(
    sc: Scenario,
    *,
    metric: str | None = None,
    seeds: int | None = None,
    workers: int | None = None,
    progress: BatchProgress | None = None,
    out: Path | None = None,
    cluster: str | None = None,
    ci_width: float | None = None,
    max_seeds: int | None = None,
) -> list[dict[str, Any]]:
    """The sweep table: one row per grid point (see the module docstring)."""
    return sweep_outcome(
        sc,
        metric=metric,
        seeds=seeds,
        workers=workers,
        progress=progress,
        out=out,
        cluster=cluster,
        ci_width=ci_width,
        max_seeds=max_seeds,
    )[0]


def sweep_outcome(
    sc: Scenario,
    *,
    metric: str | None = None,
    seeds: int | None = None,
    workers: int | None = None,
    progress: BatchProgress | None = None,
    out: Path | None = None,
    cluster: str | None = None,
    ci_width: float | None = None,
    max_seeds: int | None = None,
) -> tuple[list[dict[str, Any]], Outcome]:
    """``(rows, outcome)``: the table and the trials it was made from (per point in seed
    order); trials written to ``out`` as they finish and skipped when there (resumable).
    Interrupted: :class:`BatchInterrupted` with the complete rows as ``partial``."""
    if not sc.fusion.has_centre:
        raise ValueError("fusion.mode: peer has no fusion centre; sweep the centre modes")
    spec = sc.sweep or SweepSpec()
    metric = metric or spec.metric or sc.allocation.metrics[0]
    n_seeds = seeds or spec.seeds
    b, points = batch(sc, metric)
    burn = sc.evaluation.burn_in_scans
    try:
        outcome = run_trials(
            b,
            n_seeds,
            out=out,
            key=trial_key(sc, metric) if out is not None else None,
            workers=workers,
            cluster=cluster,
            progress=progress,
            ci_width=ci_width,
            max_seeds=max_seeds,
        )
    except BatchInterrupted as stop:  # the grid points with every seed
        done = complete_points(b, stop.done, n_seeds)
        stop.partial = rows_of(points, done, burn)
        raise
    return rows_of(points, outcome.results, burn), outcome


def rows_of(
    points: dict[str, dict[str, Any]], results: dict[str, list[dict[str, Any]]], burn_in: int
) -> list[dict[str, Any]]:
    """One row per grid point of ``results`` (point key -> its runs in seed order), in grid
    order: the means of the runs as before (``rmse_position``: the root of the mean squared
    error over seeds and scans), then the statistics over seeds
    (:func:`covnet.batches.stats.error_stats`)."""
    rows = []
    for key, p in points.items():
        rs = results.get(key)
        if not rs:
            continue
        row: dict[str, Any] = {**p, "seeds": len(rs)}
        row["rmse_position"] = float(np.sqrt(np.mean([r["pos_err2"] for r in rs])))
        for k in MEANS:
            row[k] = float(np.mean([r[k] for r in rs]))
        error_stats(
            row,
            np.asarray([r["pos_err2_scan"] for r in rs], dtype=np.float64),
            np.asarray([r["nees_scan"] for r in rs], dtype=np.float64),
            burn_in,
        )
        for k in SPREAD:
            add_stats(row, k, [r[k] for r in rs], SPREAD[k])
        row["point"] = key
        rows.append(row)
    return rows


def curves(results: dict[str, list[dict[str, Any]]]) -> dict[str, np.ndarray]:
    """The per-scan curves of every point (:func:`covnet.batches.stats.curves_of`)."""
    return curves_of(results)


def write_table(out: Path, rows: Sequence[dict[str, Any]], meta: dict[str, Any]) -> None:
    """``sweep.json`` (``meta`` and the rows) and ``sweep.csv``."""
    write_rows(out, "sweep", rows, meta, COLUMNS)


PANELS = (
    ("rmse_steady", "rmse_position", "RMSE after burn-in [m]"),
    ("rmse_transient", None, "RMSE of the burn-in scans [m]"),
    ("nees_steady", "mean_nees", "mean NEES after burn-in"),
    ("allocation_rate", "allocation_rate", "allocation rate"),
    ("deadline_miss_rate", "deadline_miss_rate", "scans missing a deadline"),
    ("late", "late", "late per run"),
    ("lost", "lost", "lost per run"),
)
"""``(statistic, the column of a table without statistics, label)``: a statistic is drawn as
its mean over seeds with the 95 % interval as a band."""


def _value(row: dict[str, Any], key: str, fallback: str | None) -> tuple[float, float, float]:
    """``(mean, lo, hi)`` of a panel's quantity in ``row`` (lo = hi = mean without an interval;
    NaN when the row has neither)."""
    mean = row.get(f"{key}_mean")
    if mean is None:
        v = row.get(key if key in row else (fallback or key))
        v = float("nan") if v is None else float(v)
        return v, v, v
    lo, hi = row.get(f"{key}_ci_lo"), row.get(f"{key}_ci_hi")
    return float(mean), float(mean if lo is None else lo), float(mean if hi is None else hi)


def make_figure(out: Path, rows: Sequence[dict[str, Any]], title: str) -> Path:
    """``sweep.png``: one row of panels per quantity, one column per fusion mode; x the mean
    one-way delay, one colour per loss level, solid ignoring loss in the allocation, dashed
    accounting for it (``late: oosm`` rows; a ``drop`` policy is drawn dotted); each statistic
    the mean over seeds with its 95 % confidence interval as a band."""
    import matplotlib  # the figure only: start-up of the runs (and of the workers)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = list(dict.fromkeys(r["mode"] for r in rows))
    losses = sorted({r["loss"] for r in rows})
    colors = plt.cm.viridis(np.linspace(0.0, 0.85, len(losses)))
    fig, axes = plt.subplots(
        len(PANELS), len(modes), figsize=(4.6 * len(modes), 2.4 * len(PANELS)), squeeze=False
    )
    for c, mode in enumerate(modes):
        for r, (key, fallback, label) in enumerate(PANELS):
            ax = axes[r, c]
            for li, loss in enumerate(losses):
                for acc in (False, True):
                    for late in ("oosm", "drop"):
                        pts = sorted(
                            (x["delay_ms"], *_value(x, key, fallback))
                            for x in rows
                            if x["mode"] == mode
                            and x["loss"] == loss
                            and x["account_for_loss"] == acc
                            and x["late_policy"] == late
                        )
                        if not pts:
                            continue
                        xs, ys, lo, hi = (np.asarray(v) for v in zip(*pts, strict=True))
                        style = ":" if late == "drop" else ("--" if acc else "-")
                        ax.plot(
                            xs,
                            ys,
                            style,
                            marker="o",
                            ms=3,
                            color=colors[li],
                            label=f"loss {loss:g}{', loss-aware' if acc else ''}"
                            f"{', drop late' if late == 'drop' else ''}",
                        )
                        if np.any(hi > lo):
                            ax.fill_between(xs, lo, hi, color=colors[li], alpha=0.15, lw=0)
            if key == "nees_steady":
                ax.axhline(4.0, color="k", lw=0.8, ls="--")
            ax.set_ylabel(label, fontsize=8)
            ax.grid(alpha=0.3)
            if r == 0:
                ax.set_title(f"fusion: {mode}")
            if r == len(PANELS) - 1:
                ax.set_xlabel("mean one-way delay [ms]")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), fontsize=8)
    burn = rows[0].get("burn_in_scans") if rows else None
    sub = (
        f"bands: 95 % t intervals over {count_range(r['seeds'] for r in rows)} seeds; "
        f"burn-in {burn} scans"
        if burn is not None
        else ""
    )
    fig.suptitle(f"{title}\n{sub}" if sub else title)
    fig.tight_layout(rect=(0, 0.04, 1, 0.98))
    path = out / "sweep.png"
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def default_curves(rows: Sequence[dict[str, Any]]) -> list[int]:
    """The points ``curves.png`` shows by default: every delay of the first mode, the lowest
    loss, loss not accounted for, the first late policy (indices into ``rows``)."""
    if not rows:
        return []
    first = rows[0]
    loss = min(r["loss"] for r in rows)
    return [
        i
        for i, r in enumerate(rows)
        if r["mode"] == first["mode"]
        and r["loss"] == loss
        and r["account_for_loss"] == first["account_for_loss"]
        and r["late_policy"] == first["late_policy"]
    ]


def curves_figure(out: Path, curves: dict[str, np.ndarray], select: Sequence[int]) -> Path:
    """``curves.png``: the per-scan RMSE and NEES of the points ``select`` (indices into
    ``curves["points"]``), each with its 95 % band over seeds (the NEES also with the
    chi-square band of a consistent filter)."""
    import matplotlib  # the figure only: start-up of the runs (and of the workers)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    colors = plt.cm.tab10(np.arange(max(len(select), 1)) % 10)
    for c, i in zip(colors, select, strict=False):
        k = np.arange(1, curves["rmse"].shape[1] + 1)
        label = f"{curves['points'][i]} ({int(curves['seeds'][i])} seeds)"
        a1.plot(k, curves["rmse"][i], color=c, lw=1.2, label=label)
        a1.fill_between(k, curves["rmse_lo"][i], curves["rmse_hi"][i], color=c, alpha=0.2, lw=0)
        a2.plot(k, curves["nees"][i], color=c, lw=1.2)
        a2.fill_between(k, curves["nees_lo"][i], curves["nees_hi"][i], color=c, alpha=0.2, lw=0)
    if len(select) == 1:
        lo, hi = curves["nees_band"][select[0]]
        a2.axhspan(lo, hi, color="0.6", alpha=0.25, label="95 % χ² band")
    a2.axhline(4.0, color="k", lw=0.8, ls="--")
    a1.set_yscale("log")
    a1.set_ylabel("position RMSE over seeds [m]")
    a2.set_ylabel("mean NEES over seeds")
    a2.set_xlabel("scan")
    a1.legend(fontsize=7)
    for ax in (a1, a2):
        ax.grid(alpha=0.3)
    fig.suptitle("per-scan curves, bands: 95 % t intervals over seeds")
    fig.tight_layout()
    path = out / "curves.png"
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def _pm(row: dict[str, Any], name: str, spec: str = ".2f") -> str:
    """``mean ± half-width`` of ``row``'s ``name`` statistics (``mean`` alone with one seed)."""
    mean = row.get(f"{name}_mean")
    if mean is None:
        return "-"
    return plus_minus(mean, row.get(f"{name}_ci_lo"), row.get(f"{name}_ci_hi"), spec, "±")


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """The table: per grid point the means as before, the steady-state RMSE (after the burn-in)
    and NEES as ``mean ± 95 % half-width`` over seeds, the transient RMSE (pooled, and its
    worst seed)."""
    head = (
        f"{'delay ms':>8} {'loss':>5} {'mode':>8} {'aware':>5} {'late':>5} {'seeds':>5} "
        f"{'RMSE m':>7} {'steady RMSE m':>13} {'transient m':>11} {'worst':>7} "
        f"{'NEES':>10} {'rate %':>6} {'miss %':>6} {'late/run':>8} {'lost/run':>8}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        tr, worst = r.get("rmse_transient"), r.get("rmse_transient_max")
        lines.append(
            f"{r['delay_ms']:>8g} {r['loss']:>5g} {r['mode']:>8} "
            f"{'yes' if r['account_for_loss'] else 'no':>5} {r['late_policy']:>5} "
            f"{r['seeds']:>5} {r['rmse_position']:>7.2f} {_pm(r, 'rmse_steady'):>13} "
            f"{'-' if tr is None else f'{tr:.2f}':>11} "
            f"{'-' if worst is None else f'{worst:.1f}':>7} "
            f"{_pm(r, 'nees_steady'):>10} "
            f"{100 * r['allocation_rate']:>6.1f} {100 * r['deadline_miss_rate']:>6.1f} "
            f"{r['late']:>8.1f} {r['lost']:>8.1f}"
        )
    if rows and rows[0].get("burn_in_scans") is not None:
        lines.append(
            f"RMSE m: every scan, as before; steady: after the first {rows[0]['burn_in_scans']} "
            "scans (evaluation.burn_in_scans), mean over seeds ± the half-width of its 95 % "
            "t interval; transient: those first scans (pooled; worst: the worst seed's); "
            f"NEES: after the burn-in, mean ± half-width (4 is consistent); {CUT}"
        )
    return "\n".join(lines)


def figure_title(meta: Mapping[str, Any]) -> str:
    """The sweep figure's title from the table's meta data (the command's, and ``covnet
    plot``'s when it redraws the figure from ``sweep.json``)."""
    fraction = meta.get("deadline_fraction")
    return (
        f"{meta.get('scenario', '')}: delay and loss ({meta.get('delay_kind', '?')} delays, "
        f"both directions), metric {meta.get('metric', '?')}, deadline "
        f"{'?' if fraction is None else f'{fraction:g}'} T"
    )
