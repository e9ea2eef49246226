"""The four figures of the paper scenario, drawn from a run directory's files only.

1. ``fig1_sensor_ellipses.png``: each sensor's measurement-uncertainty ellipse
   ``{e : eᵀ R⁻¹ e <= 1}``;
2. ``fig2_sensors_per_scan.png``: number of sensors allocated at each scan, one line per metric;
3. ``fig3_covariance_diagonal.png``: ``P11..P44`` of the filtered covariance against the desired
   levels, per metric;
4. ``fig4_allocation_raster.png``: which sensor was allocated at which scan, per metric.

Many targets (a run directory with ``target_ids``), :func:`make_target_figures`:

1. ``fig_scene.png``: per metric the area, the true trajectories (estimates dotted), each
   sensor with its coverage, and who dwelt on whom (a line from a sensor to where a target was
   while it dwelt on it, as wide as the number of scans);
2. ``fig_sensors_per_target.png``: the sensors dwelling on each target per scan, per metric;
3. ``fig_trace_per_target.png``: ``tr P_t`` against ``tr P_d,t`` per target, per metric;
4. ``fig_ospa.png``: OSPA (and GOSPA) over time, per metric;
5. ``fig_assignment_raster.png``: the target each sensor dwelt on per scan, per metric.

Plotting never re-runs a simulation: it reads ``config.json``, ``summary.json``, ``arrays.npz``.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap, to_rgba  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch, Wedge  # noqa: E402

from covnet.core.sensing import correlated_noise  # noqa: E402
from covnet.runs.rundir import load_arrays, save_figure  # noqa: E402

#: the most entries the ellipses' legend holds: beyond it the first ``LEGEND_MAX - 1`` sensors
#: are named and the last entry says how many more are drawn (256 entries do not fit a figure)
LEGEND_MAX = 64

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
    (interrupted, failed) is drawn for the scans it has, on the axes of the whole run.  A
    many-target run gets its own figures (:func:`make_target_figures`)."""
    cfg = json.loads((run_dir / "config.json").read_text())
    summary = json.loads((run_dir / "summary.json").read_text())
    arrays = load_arrays(run_dir / "arrays.npz")
    if "truth_ids" in arrays:
        # start-up: the surveillance figures only for surveillance runs
        from covnet.covariance_control.surveillance_plots import make_surveillance_figures

        return make_surveillance_figures(run_dir)
    if "target_ids" in arrays:
        return make_target_figures(run_dir, cfg, summary, arrays)
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
        named = len(ids) <= LEGEND_MAX or i < LEGEND_MAX - 1
        ax.plot(e[0], e[1], color=colors[i % 10], ls=ls, lw=1.8, label=s["id"] if named else None)
    ax.set_aspect("equal")
    ax.set_xlabel("x error (m)")
    ax.set_ylabel("y error (m)")
    ax.set_title("Sensor measurement uncertainty: {e : eᵀ R⁻¹ e ≤ 1}")
    ax.grid(alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if len(ids) > LEGEND_MAX:  # the rest are drawn, not named
        handles.append(Line2D([], [], color="none"))
        labels.append(f"and {len(ids) - len(labels)} more")
    cols = max(2, -(-len(labels) // 16))  # a large network: more, smaller legend columns
    ax.legend(
        handles,
        labels,
        ncols=cols,
        fontsize=9 if cols == 2 else 7,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
    )
    save_figure(fig, paths[0], dpi=120)
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
    save_figure(fig, paths[1], dpi=120)
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
    save_figure(fig, paths[2], dpi=120)
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
    save_figure(fig, paths[3], dpi=120)
    plt.close(fig)
    return paths


TARGET_FIGURES = (
    "fig_scene.png",
    "fig_sensors_per_target.png",
    "fig_trace_per_target.png",
    "fig_ospa.png",
    "fig_assignment_raster.png",
)
_MODEL_MARKERS = {"position": "s", "range_bearing": "^", "bearing": "o"}
_TARGET_COLOURS = (
    "tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange",
    "tab:brown", "tab:pink", "tab:gray", "tab:olive", "tab:cyan",
)  # fmt: skip


def target_colours(n: int) -> list[tuple[float, float, float, float]]:
    """``n`` colours, one a target, all different: tab10's ten, then tab20's lighter ten, then
    evenly spaced hues (the assignment raster tells targets apart only by colour; six colours
    repeated gave eight targets two shared pairs)."""
    cols = [to_rgba(c) for c in _TARGET_COLOURS]
    if n > len(cols):
        cols += [plt.get_cmap("tab20")(i) for i in range(1, 20, 2)]
    if n > len(cols):
        hsv = plt.get_cmap("hsv")
        cols += [hsv(i / (n - len(cols) + 1)) for i in range(n - len(cols))]
    return cols[:n]


def _coverage(ax: plt.Axes, s: dict[str, object], color: str) -> None:
    """A sensor's coverage: the outline of its range circle or sector (faint, dashed), in the
    scene's kilometres (the config's metres / 1000, as the sensors' markers)."""
    pos = s.get("position_m")
    rmax = s.get("max_range_m")
    if pos is None or rmax is None:
        return
    fov = s.get("fov")
    if isinstance(fov, dict):
        c, hw = float(fov["center_deg"]), float(fov["half_width_deg"])
        theta = (c - hw, c + hw)
    else:
        theta = (0.0, 360.0)
    xy = np.asarray(pos, dtype=np.float64) / 1e3
    ax.add_patch(
        Wedge(
            (float(xy[0]), float(xy[1])),
            float(rmax) / 1e3,  # type: ignore[arg-type]
            *theta,
            facecolor="none",
            alpha=0.35,
            edgecolor=color,
            lw=0.6,
            ls="--",
        )
    )


def make_target_figures(
    run_dir: Path, cfg: dict[str, object], summary: dict[str, object], arrays: dict[str, np.ndarray]
) -> list[Path]:
    """The many-target figures (module docstring) into ``run_dir``; returns their paths."""
    metrics = [str(m) for m in arrays["metrics"]]
    ids = [str(s) for s in arrays["sensor_ids"]]
    tids = [str(t) for t in arrays["target_ids"]]
    truth = arrays["truth"]
    K = truth.shape[1]
    scans = np.arange(1, K + 1)
    sensors = cfg["sensors"]
    assert isinstance(sensors, list)
    tcol = target_colours(len(tids))
    switches = summary.get("desired_switch_scans", {})
    switch_scans = (
        sorted({k for v in switches.values() for k in v[1:]}) if isinstance(switches, dict) else []
    )
    paths = [run_dir / f for f in TARGET_FIGURES]
    nm = len(metrics)

    # 1. the scene
    fig, axes = plt.subplots(1, nm, figsize=(7.2 * nm, 7.0), squeeze=False, layout="constrained")
    for ax, m in zip(axes[0], metrics, strict=True):
        asg = arrays[f"assignment.{m}"]
        x_est = arrays[f"x_est.{m}"]
        n = asg.shape[0]
        for t, tid in enumerate(tids):
            ax.plot(truth[t, :, 0] / 1e3, truth[t, :, 2] / 1e3, color=tcol[t], lw=2.0, label=tid)
            ax.plot(x_est[t, :n, 0] / 1e3, x_est[t, :n, 2] / 1e3, color=tcol[t], lw=0.8, ls=":")
            ax.plot(truth[t, 0, 0] / 1e3, truth[t, 0, 2] / 1e3, "o", color=tcol[t], ms=4)
        for j, s in enumerate(sensors):
            assert isinstance(s, dict)
            pos = s.get("position_m")
            if pos is None:
                continue
            for t in range(len(tids)):
                on = np.flatnonzero(asg[:, j] == t)
                if on.size == 0:
                    continue
                cx, cy = truth[t, on, 0].mean() / 1e3, truth[t, on, 2].mean() / 1e3
                ax.plot(
                    [pos[0] / 1e3, cx],
                    [pos[1] / 1e3, cy],
                    color=tcol[t],
                    lw=0.4 + 5.0 * on.size / max(n, 1),
                    alpha=0.45,
                )
        for j, s in enumerate(sensors):
            assert isinstance(s, dict)
            pos = s.get("position_m")
            if pos is None:
                continue
            _coverage(ax, s, "0.3")
            ax.plot(
                pos[0] / 1e3,
                pos[1] / 1e3,
                _MODEL_MARKERS.get(str(s.get("model", "position")), "s"),
                color="k",
                ms=7,
                mfc="w",
            )
            ax.annotate(ids[j], (pos[0] / 1e3, pos[1] / 1e3), xytext=(4, 4),
                        textcoords="offset points", fontsize=8)  # fmt: skip
        lo = min(0.0, float(truth[:, :, [0, 2]].min()) / 1e3) - 1.0
        hi = max(20.0, float(truth[:, :, [0, 2]].max()) / 1e3) + 1.0
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_aspect("equal")
        ax.set_xlabel("x (km)")
        ax.set_ylabel("y (km)")
        ax.set_title(
            f"{m}: truth (solid), estimates (dotted); lines: who dwelt on whom\n"
            "(□ position, △ range-bearing, ○ bearing; dashed: coverage)"
        )
        ax.grid(alpha=0.3)
        # beside the area, not over it: inside, the key hid the sensors of a corner
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    save_figure(fig, paths[0], dpi=110)
    plt.close(fig)

    # 2. sensors per target per scan
    fig, axes = plt.subplots(nm, 1, figsize=(10, 3.2 * nm), squeeze=False, layout="constrained",
                             sharex=True)  # fmt: skip
    for ax, m in zip(axes[:, 0], metrics, strict=True):
        asg = arrays[f"assignment.{m}"]
        n = asg.shape[0]
        for t, tid in enumerate(tids):
            ax.step(scans[:n], (asg == t).sum(axis=1), where="mid", color=tcol[t], lw=1.6,
                    label=tid)  # fmt: skip
        ax.step(scans[:n], (asg >= 0).sum(axis=1), where="mid", color="0.4", lw=1.0, ls="--",
                label="all")  # fmt: skip
        for k in switch_scans:
            ax.axvline(k, color="0.5", ls=":", lw=1.2)
        ax.set_xlim(0.5, K + 0.5)
        ax.set_ylim(0, len(ids) + 0.5)
        ax.set_ylabel("sensors dwelling")
        ax.set_title(f"{m}: sensors on each target per scan (dotted: priorities change)")
        ax.grid(alpha=0.3)
        ax.legend(ncols=len(tids) + 1, fontsize=9, loc="upper left")
    axes[-1, 0].set_xlabel("scan k")
    save_figure(fig, paths[1], dpi=110)
    plt.close(fig)

    # 3. tr P_t against tr P_d,t
    P_d = arrays["P_d"]
    fig, axes = plt.subplots(len(tids), 1, figsize=(10, 3.0 * len(tids)), squeeze=False,
                             layout="constrained", sharex=True)  # fmt: skip
    styles = ("-", "--", "-.", ":")
    for t, ax in enumerate(axes[:, 0]):
        for i, m in enumerate(metrics):
            P = arrays[f"P_post.{m}"][t]
            ax.plot(scans[: len(P)], np.trace(P, axis1=1, axis2=2), color=tcol[t],
                    ls=styles[i % 4], lw=1.4, label=f"tr P ({m})")  # fmt: skip
        ax.step(scans, np.trace(P_d[t], axis1=1, axis2=2), where="mid", color="k", ls="--",
                lw=1.3, label="tr P_d")  # fmt: skip
        ax.set_yscale("log")
        ax.set_ylabel(f"{tids[t]}: trace")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8, loc="upper right")
    axes[0, 0].set_title("Trace of each target's filtered covariance against its desired one")
    axes[-1, 0].set_xlabel("scan k")
    save_figure(fig, paths[2], dpi=110)
    plt.close(fig)

    # 4. OSPA over time
    fig, ax = plt.subplots(figsize=(10, 4.2), layout="constrained")
    cut = summary.get("ospa", {})
    c = cut.get("cutoff_m") if isinstance(cut, dict) else None
    for i, m in enumerate(metrics):
        o, g = arrays[f"ospa.{m}"], arrays[f"gospa.{m}"]
        col = plt.get_cmap("tab10")(i)
        ax.plot(scans[: len(o)], o, color=col, lw=1.6, label=f"OSPA ({m}), mean {o.mean():.1f} m")
        ax.plot(scans[: len(g)], g, color=col, lw=0.9, ls="--", label=f"GOSPA ({m})")
    for k in switch_scans:
        ax.axvline(k, color="0.5", ls=":", lw=1.2)
    ax.set_xlim(0.5, K + 0.5)
    ax.set_yscale("log")
    ax.set_xlabel("scan k")
    ax.set_ylabel("m")
    ax.set_title(f"OSPA and GOSPA of the target positions (cut-off c = {c} m, p = 2)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=9)
    save_figure(fig, paths[3], dpi=110)
    plt.close(fig)

    # 5. assignment raster (a large network: 10 inches a metric, every k-th sensor labelled;
    # the targets' colours in a key beside it)
    row_in = 0.3 if len(ids) <= 32 else 10.0 / len(ids)
    tick = max(1, -(-len(ids) // 32))
    fig, axes = plt.subplots(nm, 1, figsize=(11, 1.2 + row_in * len(ids) * nm), squeeze=False,
                             layout="constrained", sharex=True)  # fmt: skip
    cmap = ListedColormap([to_rgba("white"), *tcol])
    key = [Patch(facecolor=c, label=tid) for tid, c in zip(tids, tcol, strict=True)]
    key.append(Patch(facecolor="white", edgecolor="0.5", label="off"))
    for ax, m in zip(axes[:, 0], metrics, strict=True):
        asg = arrays[f"assignment.{m}"].T + 1
        ax.imshow(asg, aspect="auto", cmap=cmap, vmin=0, vmax=len(tids), interpolation="nearest",
                  extent=(0.5, asg.shape[1] + 0.5, len(ids) - 0.5, -0.5))  # fmt: skip
        ax.set_xlim(0.5, K + 0.5)
        ax.set_yticks(range(0, len(ids), tick), ids[::tick])
        ax.set_ylabel("sensor")
        ax.set_title(f"{m}: the target each sensor dwelt on")
        ax.legend(handles=key, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8,
                  ncols=-(-len(key) // 24))  # fmt: skip
        for k in switch_scans:
            ax.axvline(k, color="k", ls=":", lw=1.0)
    axes[-1, 0].set_xlabel("scan k")
    save_figure(fig, paths[4], dpi=110)
    plt.close(fig)
    return paths


def mc_figure(mc_dir: Path) -> Path:
    """``montecarlo.png`` of a ``covnet mc`` directory: per metric the mean OSPA per scan (many
    targets) and each target's mean ``tr P_t`` against ``tr P_d,t``, with 95 % intervals."""
    doc = json.loads((mc_dir / "montecarlo.json").read_text())
    agg = doc["aggregate"]
    if doc.get("surveillance"):
        # start-up: the surveillance figures only for surveillance batches
        from covnet.covariance_control.surveillance_plots import mc_figure as surv_mc_figure

        return surv_mc_figure(mc_dir, doc)
    metrics = list(agg)
    tids = list(next(iter(agg.values()))["targets"]) if agg else []
    has_ospa = bool(agg) and "ospa_per_scan" in next(iter(agg.values()))
    rows = len(tids) + (1 if has_ospa else 0)
    fig, axes = plt.subplots(max(rows, 1), 1, figsize=(10, 2.8 * max(rows, 1)), squeeze=False,
                             layout="constrained", sharex=True)  # fmt: skip
    ax_list = list(axes[:, 0])
    n = len(doc["seeds"])
    if has_ospa:
        ax = ax_list.pop(0)
        for i, m in enumerate(metrics):
            s = agg[m]["ospa_per_scan"]
            k = np.arange(1, len(s["mean"]) + 1)
            col = plt.get_cmap("tab10")(i)
            ax.plot(k, s["mean"], color=col, lw=1.5, label=f"{m}")
            if s["ci95_low"] is not None:  # one seed: no interval
                ax.fill_between(k, s["ci95_low"], s["ci95_high"], color=col, alpha=0.2)
        ax.set_ylabel("OSPA (m)")
        ax.set_ylim(bottom=0.0)
        ax.set_title(f"{doc['scenario']}: means over {n} seeds with 95 % intervals")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=9)
    for t, (tid, ax) in enumerate(zip(tids, ax_list, strict=True)):
        for i, m in enumerate(metrics):
            s = agg[m]["targets"][tid]["trace_P_per_scan"]
            k = np.arange(1, len(s["mean"]) + 1)
            col = plt.get_cmap("tab10")(i)
            ax.plot(k, s["mean"], color=col, lw=1.4, label=f"tr P ({m})")
            if s["ci95_low"] is not None:  # one seed: no interval
                ax.fill_between(k, s["ci95_low"], s["ci95_high"], color=col, alpha=0.2)
        pd_ = doc.get("trace_Pd", {}).get(tid)
        if pd_:
            ax.step(np.arange(1, len(pd_) + 1), pd_, where="mid", color="k", ls="--", lw=1.2,
                    label="tr P_d")  # fmt: skip
            ax.set_ylim(0.0, 3.0 * max(pd_))  # a lost track's seeds widen the interval a lot
        ax.set_ylabel(f"{tid}: trace")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8, loc="upper right")
        if t == 0 and not has_ospa:
            ax.set_title(f"{doc['scenario']}: means over {n} seeds with 95 % intervals")
    axes[-1, 0].set_xlabel("scan k")
    path = mc_dir / "montecarlo.png"
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path
