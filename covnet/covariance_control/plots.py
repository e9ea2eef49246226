"""The four figures of the paper scenario, drawn from a run directory's files only.

1. ``fig1_sensor_ellipses.png``: each sensor's measurement-uncertainty ellipse
   ``{e : eᵀ R⁻¹ e <= 1}``;
2. ``fig2_sensors_per_scan.png``: number of sensors allocated at each scan, one line per metric;
3. ``fig3_covariance_diagonal.png``: ``P11..P44`` of the filtered covariance against the desired
   levels, per metric;
4. ``fig4_allocation_raster.png``: which sensor was allocated at which scan, per metric.

Plotting never re-runs a simulation: it reads ``config.json``, ``summary.json``, ``arrays.npz``.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402

from covnet.core.sensing import correlated_noise  # noqa: E402
from covnet.rundir import load_arrays  # noqa: E402

FIGURES = (
    "fig1_sensor_ellipses.png",
    "fig2_sensors_per_scan.png",
    "fig3_covariance_diagonal.png",
    "fig4_allocation_raster.png",
)
_DIAG_LABELS = (
    ("P11", "x position", "m²"),
    ("P22", "x velocity", "m²/s²"),
    ("P33", "y position", "m²"),
    ("P44", "y velocity", "m²/s²"),
)


def ellipse_points(R: np.ndarray, n: int = 200) -> np.ndarray:
    """Boundary of ``{e : eᵀ R⁻¹ e = 1}``: ``e = L [cos θ, sin θ]`` with ``R = L Lᵀ``."""
    th = np.linspace(0.0, 2.0 * np.pi, n)
    return np.linalg.cholesky(R) @ np.vstack([np.cos(th), np.sin(th)])


def _switch_lines(ax: plt.Axes, switches: list[int], color: str = "0.5") -> None:
    for s in switches[1:]:
        ax.axvline(s, color=color, ls=":", lw=1.2)


def make_figures(run_dir: Path) -> list[Path]:
    """Draw the four figures into ``run_dir``; returns their paths.  A run that ended early
    (interrupted, failed) is drawn for the scans it has, on the axes of the whole run."""
    cfg = json.loads((run_dir / "config.json").read_text())
    summary = json.loads((run_dir / "summary.json").read_text())
    arrays = load_arrays(run_dir / "arrays.npz")
    metrics = [str(m) for m in arrays["metrics"]]
    ids = [str(s) for s in arrays["sensor_ids"]]
    t_scan = np.arange(1, len(arrays["t"]) + 1)
    switches = summary.get("desired_switch_scans", [1])
    colors = [plt.get_cmap("tab10")(i) for i in range(10)]
    paths = [run_dir / f for f in FIGURES]

    # 1. measurement-uncertainty ellipses
    fig, ax = plt.subplots(figsize=(7, 6.5), layout="constrained")
    for i, s in enumerate(cfg["sensors"]):
        e = ellipse_points(correlated_noise(s["sigma_x_m"], s["sigma_y_m"], s["rho"]))
        ls = "-" if i < 10 else "--"
        ax.plot(e[0], e[1], color=colors[i % 10], ls=ls, lw=1.8, label=s["id"])
    ax.set_aspect("equal")
    ax.set_xlabel("x error (m)")
    ax.set_ylabel("y error (m)")
    ax.set_title("Sensor measurement uncertainty: {e : eᵀ R⁻¹ e ≤ 1}")
    ax.grid(alpha=0.3)
    cols = max(2, -(-len(ids) // 16))  # a large network: more, smaller legend columns
    ax.legend(
        ncols=cols, fontsize=9 if cols == 2 else 7, loc="upper left", bbox_to_anchor=(1.01, 1.0)
    )
    fig.savefig(paths[0], dpi=120)
    plt.close(fig)

    # 2. sensors allocated per scan
    fig, ax = plt.subplots(figsize=(9, 4.5), layout="constrained")
    for i, m in enumerate(metrics):
        blk = summary["metrics"][m]
        counts = blk["sensors_per_scan"]
        lbl = f"{m} (rate {100 * blk['allocation_rate']:.1f} %)"
        ax.step(t_scan[: len(counts)], counts, where="mid", color=colors[i % 10], lw=1.8, label=lbl)
    ax.set_xlim(0.5, len(t_scan) + 0.5)
    _switch_lines(ax, switches)
    ax.set_xlabel("scan k")
    ax.set_ylabel("sensors allocated N_k")
    ax.set_ylim(0, len(ids) + 0.5)
    ax.set_title("Sensors allocated per scan (dotted: desired covariance changes)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.savefig(paths[1], dpi=120)
    plt.close(fig)

    # 3. diagonal of P vs the desired levels
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), layout="constrained", sharex=True)
    P_d = arrays["P_d"]
    for d, ax in enumerate(axes.ravel()):
        name, what, unit = _DIAG_LABELS[d]
        for i, m in enumerate(metrics):
            P = arrays[f"P_post.{m}"]
            ax.plot(t_scan[: len(P)], P[:, d, d], color=colors[i % 10], lw=1.5, label=m)
        ax.step(t_scan, P_d[:, d, d], where="mid", color="k", ls="--", lw=1.5, label="desired")
        ax.set_yscale("log")
        ax.set_title(f"{name}: {what} variance")
        ax.set_ylabel(f"{name} ({unit})")
        ax.grid(alpha=0.3, which="both")
        _switch_lines(ax, switches)
    for ax in axes[1]:
        ax.set_xlabel("scan k")
    axes[0, 0].legend(fontsize=9)
    fig.suptitle("Diagonal of the filtered covariance P(k|k) against the desired covariance")
    fig.savefig(paths[2], dpi=120)
    plt.close(fig)

    # 4. allocation raster (a large network: 5 inches a metric, every k-th sensor labelled)
    row_in = 0.32 if len(ids) <= 16 else 5.0 / len(ids)
    tick = max(1, -(-len(ids) // 16))
    fig, axes = plt.subplots(
        len(metrics),
        1,
        figsize=(10, 1.2 + row_in * len(ids) * len(metrics)),
        squeeze=False,
        layout="constrained",
        sharex=True,
    )
    cmap = ListedColormap(["white", "tab:blue"])
    for ax, m in zip(axes[:, 0], metrics, strict=True):
        en = arrays[f"enabled.{m}"].T.astype(float)
        ax.imshow(
            en,
            aspect="auto",
            cmap=cmap,
            vmin=0,
            vmax=1,
            interpolation="nearest",
            extent=(0.5, en.shape[1] + 0.5, len(ids) - 0.5, -0.5),
        )
        ax.set_xlim(0.5, len(t_scan) + 0.5)
        ax.set_yticks(range(0, len(ids), tick), ids[::tick])
        ax.set_ylabel("sensor")
        rate = 100 * summary["metrics"][m]["allocation_rate"]
        ax.set_title(f"{m}: sensors allocated (filled) per scan, rate {rate:.1f} %")
        _switch_lines(ax, switches, color="tab:red")
    axes[-1, 0].set_xlabel("scan k")
    fig.savefig(paths[3], dpi=120)
    plt.close(fig)
    return paths
