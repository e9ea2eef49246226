"""The mobile run's figure, drawn from a run directory's files only.

``fig_mobile_trajectories.png``:

* left: the plane, true target trajectories (estimates dotted), platform trajectories, and the
  assignments (a line from the sensor to its target) every few scans;
* right, top: which sensor observed each target at each scan (blank: unobserved; x: assigned
  but missed);
* right, bottom: the position error of every track per scan.

Plotting never re-runs a simulation: it reads ``config.json``, ``summary.json``, ``arrays.npz``.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.artist import Artist  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from covnet.batches.stats import t_half_width  # noqa: E402
from covnet.runs.rundir import load_arrays, save_figure  # noqa: E402

FIGURE = "fig_mobile_trajectories.png"
SENSOR_COLORS = (
    "tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple",
    "tab:cyan", "tab:olive", "tab:pink", "tab:gray", "tab:brown",
)  # fmt: skip
TARGET_COLORS = ("#222222", "#8c564b", "#b5179e", "#4d4d4d", "#7a5c00", "#005f73")


def _every(K: int) -> int:
    return max(1, int(round(K / 20)))


def make_figure(run_dir: Path) -> Path:
    """Draw the figure into ``run_dir``; returns its path."""
    summary = json.loads((run_dir / "summary.json").read_text())
    arr = load_arrays(run_dir / "arrays.npz")
    tids = [str(t) for t in arr["target_ids"]]
    sids = [str(s) for s in arr["sensor_ids"]]
    X, Xe, A = arr["truth"], arr["x_est"], arr["platforms"]
    assign, detected = arr["assign"], arr["detected"]
    K, M = assign.shape
    N = A.shape[1]
    sc = [SENSOR_COLORS[j % len(SENSOR_COLORS)] for j in range(N)]
    tc = [TARGET_COLORS[i % len(TARGET_COLORS)] for i in range(M)]
    scans = np.arange(1, K + 1)

    fig = plt.figure(figsize=(15, 7.8), layout="constrained")
    gs = fig.add_gridspec(2, 2, width_ratios=(1.05, 1.0), height_ratios=(1.0, 1.0))
    ax = fig.add_subplot(gs[:, 0])
    ax_a = fig.add_subplot(gs[0, 1])
    ax_e = fig.add_subplot(gs[1, 1], sharex=ax_a)

    # the plane
    stride = _every(K)
    for k in range(stride, K + 1, stride):
        for ii in np.flatnonzero(assign[k - 1] >= 0):
            jj = assign[k - 1, ii]
            ax.plot(
                [A[k, jj, 0], X[k, ii, 0]], [A[k, jj, 1], X[k, ii, 2]],
                color=sc[jj], lw=0.8, alpha=0.55, zorder=1,
            )  # fmt: skip
    for i in range(M):
        ax.plot(X[:, i, 0], X[:, i, 2], color=tc[i], lw=2.0, zorder=3)
        ax.plot(Xe[:, i, 0], Xe[:, i, 2], color=tc[i], lw=1.0, ls=":", zorder=3)
        ax.plot(X[0, i, 0], X[0, i, 2], "o", color=tc[i], ms=6, zorder=4)
        ax.plot(X[-1, i, 0], X[-1, i, 2], "D", color=tc[i], ms=6, zorder=4)
        ax.annotate(
            tids[i],
            (X[0, i, 0], X[0, i, 2]),
            xytext=(6, -12),
            textcoords="offset points",
            color=tc[i],
            fontsize=11,
            weight="bold",
        )
    for j in range(N):
        ax.plot(A[:, j, 0], A[:, j, 1], color=sc[j], lw=3.0, alpha=0.85, zorder=2)
        ax.plot(A[0, j, 0], A[0, j, 1], "s", color=sc[j], ms=9, mec="k", zorder=5)
        ax.plot(A[-1, j, 0], A[-1, j, 1], "^", color=sc[j], ms=9, mec="k", zorder=5)
        ax.annotate(
            sids[j],
            (A[0, j, 0], A[0, j, 1]),
            xytext=(6, 6),
            textcoords="offset points",
            color=sc[j],
            fontsize=11,
            weight="bold",
        )
    handles = [
        Line2D([], [], color="k", lw=2.0, label="target truth (o start, ◆ end)"),
        Line2D([], [], color="k", lw=1.0, ls=":", label="target estimate"),
        Line2D([], [], color="0.4", lw=3.0, label="platform path (■ start, ▲ end)"),
        Line2D([], [], color="0.4", lw=0.8, label=f"assignment (every {stride} scans)"),
    ]
    ax.legend(handles=handles, loc="best", fontsize=9, framealpha=0.9)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    ax.set_title("Targets, sensor platforms and assignments")

    # assignments over time
    img = np.where(assign >= 0, assign + 1, 0).T.astype(float)  # (M, K); 0 = unobserved
    cmap = ListedColormap(["white", *sc])
    ax_a.imshow(
        img, aspect="auto", cmap=cmap, vmin=-0.5, vmax=N + 0.5, interpolation="nearest",
        extent=(0.5, K + 0.5, M - 0.5, -0.5),
    )  # fmt: skip
    miss_k, miss_i = np.nonzero((assign >= 0) & ~detected)
    ax_a.plot(miss_k + 1, miss_i, "x", color="k", ms=4, mew=1.0)
    ax_a.set_yticks(range(M), tids)
    ax_a.set_ylabel("target")
    ax_a.tick_params(labelbottom=False)
    ax_a.set_title("Sensor observing each target per scan")
    leg: list[Artist] = [Patch(facecolor=sc[j], label=sids[j]) for j in range(N)]
    leg += [
        Patch(facecolor="white", edgecolor="0.5", label="unobserved"),
        Line2D([], [], marker="x", color="k", ls="", label="missed detection"),
    ]
    ax_a.legend(handles=leg, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)

    # position error
    err = np.hypot(Xe[1:, :, 0] - X[1:, :, 0], Xe[1:, :, 2] - X[1:, :, 2])
    for i in range(M):
        rm = summary["targets"][tids[i]]["rmse_position_m"]
        ax_e.plot(scans, err[:, i], color=tc[i], lw=1.4, label=f"{tids[i]} (RMSE {rm:.2f} m)")
    ax_e.set_yscale("log")
    ax_e.set_xlabel("scan k")
    ax_e.set_ylabel("position error (m)")
    ax_e.grid(alpha=0.3, which="both")
    ax_e.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    ax_e.set_title("Track position error ‖p̂ − p‖")

    ov = summary["overall"]
    fig.suptitle(
        f"{summary['scenario']}: seed {summary['seed']}, solver {summary['solver']}, "
        f"{K} scans — missed detections {100 * ov['missed_detection_rate']:.1f} % "
        f"(2nd half {100 * ov['missed_detection_rate_second_half']:.1f} %), "
        f"platform travel {summary['platform_travel_m']['total']:.0f} m"
    )
    path = run_dir / FIGURE
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


MC_FIGURE = "fig_mobile_mc.png"


def _mean_ci(values: np.ndarray) -> tuple[float, float]:
    """The mean over seeds and the half-width of its 95 % confidence interval (Student t;
    0 for a single seed)."""
    n = values.size
    mean = float(values.mean())
    if n < 2:
        return mean, 0.0
    half = float(t_half_width(values.std(ddof=1), n))
    return mean, half


def mc_figure(out_dir: Path) -> Path:
    """``fig_mobile_mc.png`` from ``out_dir/montecarlo.json``: per target (and overall) the
    position RMSE and the missed-detection rate, second half of the run and whole run, as the
    mean over seeds with its 95 % confidence interval (the axes cut at the quantities' own
    limits, 0 and a rate's 1: Student's interval of a few seeds reaches beyond)."""
    doc = json.loads((out_dir / "montecarlo.json").read_text())
    rows = doc["per_seed"]
    names = [*rows[0]["target_ids"], "overall"]

    def block(r: dict[str, object], name: str) -> dict[str, float]:
        b = r["overall"] if name == "overall" else r["targets"][name]  # type: ignore[index]
        return b  # type: ignore[return-value]

    panels = (  # (whole run, second half, label, the quantity's upper limit)
        ("rmse_position_m", "rmse_position_second_half_m", "position RMSE [m]", None),
        ("missed_detection_rate", "missed_detection_rate_second_half", "missed detections", 1.0),
    )
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), layout="constrained")
    x = np.arange(len(names))
    for ax, (whole, second, label, top) in zip(axes, panels, strict=True):
        for dx, key, tag in ((-0.18, whole, "whole run"), (0.18, second, "second half")):
            stats = [_mean_ci(np.array([block(r, n)[key] for r in rows])) for n in names]
            means, halves = zip(*stats, strict=True)
            ax.bar(x + dx, means, 0.36, yerr=halves, capsize=4, label=tag)
        # an RMSE is >= 0 and a rate in [0, 1]: a few seeds' t-interval reaches beyond (cut)
        hi = ax.get_ylim()[1]
        ax.set_ylim(0.0, hi if top is None else min(hi, top))
        ax.set_xticks(x, names)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
        ax.legend()
    fig.suptitle(
        f"{doc['scenario']}: Monte Carlo over {len(rows)} seeds, solver {doc['solver']} "
        "(mean, 95 % confidence interval)"
    )
    path = out_dir / MC_FIGURE
    save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path
