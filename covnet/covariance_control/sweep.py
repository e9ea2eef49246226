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

Runs go to a ``spawn`` process pool (one per core); ``sweep.csv``, ``sweep.json`` and
``sweep.png`` are written to the output directory.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from covnet.batch import BatchInterrupted, Progress, parallel_map, write_rows
from covnet.covariance_control.config import Scenario, SweepSpec, from_dict, normalised
from covnet.covariance_control.latency_sim import run_latency
from covnet.covariance_control.model import build_model, truth_trajectory

POINT_KEYS = ("delay_ms", "loss", "mode", "account_for_loss", "late_policy")
COLUMNS = (
    *POINT_KEYS,
    "seeds",
    "rmse_position",
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
    return from_dict(data, f"{sc.name} (sweep point)")


def grid(spec: SweepSpec) -> list[dict[str, Any]]:
    """Every grid point, in a fixed order."""
    return [
        dict(zip(POINT_KEYS, values, strict=True))
        for values in itertools.product(
            spec.delay_ms, spec.loss, spec.modes, spec.account_for_loss, spec.late
        )
    ]


def run_point(task: tuple[dict[str, Any], dict[str, Any], int, str]) -> dict[str, Any]:
    """One run at one grid point (a module-level function: the pool's workers import it)."""
    data, point, seed, metric = task
    sc = point_scenario(from_dict(data), point, seed)
    model = build_model(sc)
    run, counts = run_latency(sc, metric, model)
    err = run.x_est - truth_trajectory(model)
    c = counts.as_dict()
    return {
        **point,
        "seed": seed,
        "pos_err2": float(np.mean(err[:, 0] ** 2 + err[:, 2] ** 2)),
        "mean_nees": float(run.nees[10:].mean() if len(run.nees) > 10 else run.nees.mean()),
        "allocation_rate": float(run.enabled.mean()),
        "deadline_miss_rate": c["deadline_misses"] / len(run.value),
        "late": c["late_refiltered"] + c["late_dropped"],
        "fused": c["on_time"] + c["late_refiltered"],
        **{
            k: c[k]
            for k in ("late_refiltered", "late_dropped", "lost", "commands_missed", "measured")
        },
    }


def sweep(
    sc: Scenario,
    *,
    metric: str | None = None,
    seeds: int | None = None,
    workers: int | None = None,
    progress: Progress | None = None,
) -> list[dict[str, Any]]:
    """The sweep table: one row per grid point (see the module docstring)."""
    if sc.fusion.mode == "peer":
        raise ValueError("fusion.mode: peer has no fusion centre; sweep the centre modes")
    spec = sc.sweep or SweepSpec()
    metric = metric or spec.metric or sc.allocation.metrics[0]
    n_seeds = seeds or spec.seeds
    points = grid(spec)
    data = normalised(sc)
    tasks = [(data, p, sc.seed + r, metric) for p in points for r in range(n_seeds)]
    try:
        runs = parallel_map(run_point, tasks, workers, progress)
    except BatchInterrupted as stop:
        stop.partial = _rows(points, n_seeds, stop.done)  # the grid points with every seed
        raise
    return _rows(points, n_seeds, dict(enumerate(runs)))


def _rows(
    points: Sequence[dict[str, Any]], n_seeds: int, runs: dict[int, dict[str, Any]]
) -> list[dict[str, Any]]:
    """One row per grid point all of whose ``n_seeds`` runs are in ``runs`` (task index ->
    run; point ``i``'s seeds are the tasks ``i n_seeds .. (i + 1) n_seeds - 1``)."""
    rows = []
    for i, p in enumerate(points):
        idx = range(i * n_seeds, (i + 1) * n_seeds)
        if not all(j in runs for j in idx):
            continue
        rs = [runs[j] for j in idx]
        row: dict[str, Any] = {**p, "seeds": n_seeds}
        row["rmse_position"] = float(np.sqrt(np.mean([r["pos_err2"] for r in rs])))
        for k in COLUMNS[len(POINT_KEYS) + 2 :]:
            row[k] = float(np.mean([r[k] for r in rs]))
        rows.append(row)
    return rows


def write_table(out: Path, rows: Sequence[dict[str, Any]], meta: dict[str, Any]) -> None:
    """``sweep.json`` (``meta`` and the rows) and ``sweep.csv``."""
    write_rows(out, "sweep", rows, meta, COLUMNS)


PANELS = (
    ("rmse_position", "position RMSE [m]"),
    ("mean_nees", "mean NEES (4 states)"),
    ("allocation_rate", "allocation rate"),
    ("deadline_miss_rate", "scans missing a deadline"),
    ("late", "late per run"),
    ("lost", "lost per run"),
)


def make_figure(out: Path, rows: Sequence[dict[str, Any]], title: str) -> Path:
    """``sweep.png``: one row of panels per quantity, one column per fusion mode; x the mean
    one-way delay, one colour per loss level, solid ignoring loss in the allocation, dashed
    accounting for it (``late: oosm`` rows; a ``drop`` policy is drawn dotted)."""
    import matplotlib  # the figure only: start-up of the runs (and of the workers)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = list(dict.fromkeys(r["mode"] for r in rows))
    losses = sorted({r["loss"] for r in rows})
    colors = plt.cm.viridis(np.linspace(0.0, 0.85, len(losses)))
    fig, axes = plt.subplots(
        len(PANELS), len(modes), figsize=(4.6 * len(modes), 2.5 * len(PANELS)), squeeze=False
    )
    for c, mode in enumerate(modes):
        for r, (key, label) in enumerate(PANELS):
            ax = axes[r, c]
            for li, loss in enumerate(losses):
                for acc in (False, True):
                    for late in ("oosm", "drop"):
                        pts = sorted(
                            (x["delay_ms"], x[key])
                            for x in rows
                            if x["mode"] == mode
                            and x["loss"] == loss
                            and x["account_for_loss"] == acc
                            and x["late_policy"] == late
                        )
                        if not pts:
                            continue
                        style = ":" if late == "drop" else ("--" if acc else "-")
                        ax.plot(
                            *zip(*pts, strict=True),
                            style,
                            marker="o",
                            ms=3,
                            color=colors[li],
                            label=f"loss {loss:g}{', loss-aware' if acc else ''}"
                            f"{', drop late' if late == 'drop' else ''}",
                        )
            if key == "mean_nees":
                ax.axhline(4.0, color="k", lw=0.8, ls="--")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
            if r == 0:
                ax.set_title(f"fusion: {mode}")
            if r == len(PANELS) - 1:
                ax.set_xlabel("mean one-way delay [ms]")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), fontsize=8)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.04, 1, 0.98))
    path = out / "sweep.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    head = (
        f"{'delay ms':>8} {'loss':>5} {'mode':>8} {'aware':>5} {'late':>5} {'RMSE m':>7} "
        f"{'NEES':>5} {'rate %':>6} {'miss %':>6} {'late/run':>8} {'lost/run':>8}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['delay_ms']:>8g} {r['loss']:>5g} {r['mode']:>8} "
            f"{'yes' if r['account_for_loss'] else 'no':>5} {r['late_policy']:>5} "
            f"{r['rmse_position']:>7.2f} {r['mean_nees']:>5.2f} "
            f"{100 * r['allocation_rate']:>6.1f} {100 * r['deadline_miss_rate']:>6.1f} "
            f"{r['late']:>8.1f} {r['lost']:>8.1f}"
        )
    return "\n".join(lines)
