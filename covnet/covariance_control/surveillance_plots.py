"""The figures of a surveillance run directory (spec ``surveillance.md`` §5), drawn from its
``arrays.npz`` and ``summary.json`` alone:

- ``fig_scene.png``: the area, the search cells shaded by their undetected mass ``u_c`` after
  the last scan, the sensors, every target's true path (start marked), and the first metric's
  tracks: confirmed (solid), tentative (dotted), the scans where a track was deleted (x);
- ``fig_cardinality.png``: confirmed tracks against true targets per scan (tentative shaded);
- ``fig_gospa.png``: GOSPA per scan with its decomposition (localisation, missed, false: the
  ``p``-th powers GOSPA sums, stacked), and OSPA;
- ``fig_search.png``: dwells per scan on search against dwells on tracks, and ``Σ u_c``;
- ``fig_confirm.png``: per target the scans from its appearance to its first confirmed track.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from covnet.runs.rundir import load_arrays, save_figure  # noqa: E402

__all__ = ["FIGURES", "make_surveillance_figures", "mc_figure"]

FIGURES = ("fig_scene.png", "fig_cardinality.png", "fig_gospa.png", "fig_search.png",
           "fig_confirm.png")  # fmt: skip


def _tracks(rows: np.ndarray) -> dict[int, dict[str, Any]]:
    """``track_rows`` as per-track series: scans, states and positions."""
    out: dict[int, dict[str, Any]] = {}
    for r in rows:
        d = out.setdefault(int(r[1]), {"scan": [], "state": [], "xy": []})
        d["scan"].append(int(r[0]))
        d["state"].append(int(r[2]))
        d["xy"].append((r[3], r[5]))
    return out


def make_surveillance_figures(run_dir: Path) -> list[Path]:
    """Draw the figures (module docstring) into ``run_dir``; returns their paths."""
    cfg = json.loads((run_dir / "config.json").read_text())
    summary = json.loads((run_dir / "summary.json").read_text())
    a = load_arrays(run_dir / "arrays.npz")
    metrics = [str(m) for m in a["metrics"]]
    m0 = metrics[0]
    paths = [run_dir / f for f in FIGURES]
    truth, ids = a["truth"], [str(t) for t in a["truth_ids"]]
    colors = [plt.get_cmap("tab10")(i) for i in range(10)]
    area = cfg["surveillance"]["area"]

    # 1. the scene
    fig, ax = plt.subplots(figsize=(8.5, 7.5), layout="constrained")
    cells, u = a["cells"], a[f"u.{m0}"]
    if len(cells) and len(u):
        last = u[-1]
        top = max(float(last.max()), 1e-12)
        for c, (x0, x1, y0, y1) in enumerate(cells):
            ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, color="tab:orange",
                                       alpha=0.05 + 0.45 * float(last[c]) / top, lw=0))  # fmt: skip
            ax.text((x0 + x1) / 2, (y0 + y1) / 2, f"{last[c]:.2f}", ha="center",
                    va="center", fontsize=7, color="0.35")  # fmt: skip
    for s in cfg["sensors"]:
        if s.get("position_m"):
            ax.plot(*s["position_m"], marker="^", color="0.3", ms=6)
            ax.annotate(s["id"], s["position_m"], fontsize=7, xytext=(3, 3),
                        textcoords="offset points")  # fmt: skip
    for i, tid in enumerate(ids):
        xy = truth[i][:, [0, 2]]
        ok = np.all(np.isfinite(xy), axis=1)
        if ok.any():
            ax.plot(xy[ok, 0], xy[ok, 1], color="k", lw=2.2, alpha=0.35)
            first = xy[ok][0]
            ax.plot(*first, "ko", ms=4)
            ax.annotate(tid, first, fontsize=8, xytext=(4, -10), textcoords="offset points")
    tr = _tracks(a[f"track_rows.{m0}"])
    for n, (_tid, d) in enumerate(sorted(tr.items())):
        xy, st = np.array(d["xy"]), np.array(d["state"])
        col = colors[n % 10]
        conf = st == 1
        if conf.any():
            ax.plot(xy[conf, 0], xy[conf, 1], color=col, lw=1.2)
        if (~conf).any():
            ax.plot(xy[~conf, 0], xy[~conf, 1], color=col, lw=0.8, ls=":")
        dead = st == 2
        if dead.any():
            ax.plot(xy[dead, 0], xy[dead, 1], "x", color=col, ms=5)
    # a margin round the area: sensors stand on its edges and corners, and their names
    # would otherwise run into the title
    pad = 0.05 * max(area["max_m"][0] - area["min_m"][0], area["max_m"][1] - area["min_m"][1])
    ax.set_xlim(area["min_m"][0] - pad, area["max_m"][0] + pad)
    ax.set_ylim(area["min_m"][1] - pad, area["max_m"][1] + pad)
    ax.add_patch(plt.Rectangle((area["min_m"][0], area["min_m"][1]),
                               area["max_m"][0] - area["min_m"][0],
                               area["max_m"][1] - area["min_m"][1],
                               fill=False, ec="0.5", lw=0.8))  # fmt: skip
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{m0}: truth (grey), tracks (solid confirmed, dotted tentative, x deleted); "
                 "cells: u_c after the last scan", fontsize=9)  # fmt: skip
    save_figure(fig, paths[0], dpi=110)
    plt.close(fig)

    K = len(a[f"gospa.{m0}"])
    k = np.arange(1, K + 1)
    # 2. cardinality
    fig, ax = plt.subplots(figsize=(9, 4), layout="constrained")
    ax.step(k, a[f"n_truth.{m0}"], where="mid", color="k", lw=2, label="true targets")
    for i, m in enumerate(metrics):
        nc, nt = a[f"n_confirmed.{m}"], a[f"n_tentative.{m}"]
        ax.step(k, nc, where="mid", color=colors[i], lw=1.6, label=f"{m}: confirmed")
        ax.fill_between(k, nc, nc + nt, step="mid", color=colors[i], alpha=0.15,
                        label=f"{m}: + tentative")  # fmt: skip
    ax.set_xlabel("scan k")
    ax.set_ylabel("number")
    ax.set_title("Cardinality: confirmed tracks against true targets")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    save_figure(fig, paths[1], dpi=110)
    plt.close(fig)

    # 3. GOSPA and its decomposition
    fig, axes = plt.subplots(len(metrics), 1, figsize=(9, 3.2 * len(metrics)), squeeze=False,
                             layout="constrained")  # fmt: skip
    for i, m in enumerate(metrics):
        ax = axes[i, 0]
        parts = [a[f"gospa_loc.{m}"], a[f"gospa_missed.{m}"], a[f"gospa_false.{m}"]]
        ax.stackplot(k, *parts, labels=["localisation", "missed", "false"],
                     colors=["tab:blue", "tab:red", "tab:gray"], alpha=0.6)  # fmt: skip
        ax.set_ylabel("GOSPA^p parts (m^p)")
        ax2 = ax.twinx()
        ax2.plot(k, a[f"gospa.{m}"], color="k", lw=1.4, label="GOSPA")
        ax2.plot(k, a[f"ospa.{m}"], color="k", ls="--", lw=1.0, label="OSPA")
        ax2.set_ylabel("distance (m)")
        b = summary["metrics"][m]
        ax.set_title(f"{m}: mean GOSPA {b['gospa_mean']:.1f} m, OSPA {b['ospa_mean']:.1f} m")
        ax.legend(loc="upper left", fontsize=8)
        ax2.legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("scan k")
    save_figure(fig, paths[2], dpi=110)
    plt.close(fig)

    # 4. search against track
    fig, ax = plt.subplots(figsize=(9, 4), layout="constrained")
    for i, m in enumerate(metrics):
        ax.step(k, a[f"search_dwells.{m}"], where="mid", color=colors[i], lw=1.6,
                label=f"{m}: search dwells")  # fmt: skip
        ax.step(k, a[f"track_dwells.{m}"], where="mid", color=colors[i], lw=1.0, ls="--",
                label=f"{m}: track dwells")  # fmt: skip
    ax.set_xlabel("scan k")
    ax.set_ylabel("dwells")
    ax2 = ax.twinx()
    ax2.plot(k, a[f"u.{m0}"].sum(axis=1) if len(cells) else np.zeros(K), color="tab:orange",
             lw=1.4, label="Σ u_c (undetected)")  # fmt: skip
    ax2.set_ylabel("Σ u_c")
    ax.set_title(f"Search against track (search weight λ = {summary['search_weight']:g})")
    ax.legend(loc="upper left", fontsize=8)
    ax2.legend(loc="upper right", fontsize=8)
    save_figure(fig, paths[3], dpi=110)
    plt.close(fig)

    # 5. time to confirm
    fig, ax = plt.subplots(figsize=(9, 3.8), layout="constrained")
    width = 0.8 / len(metrics)
    x = np.arange(len(ids))
    for i, m in enumerate(metrics):
        v = a[f"time_to_confirm.{m}"]
        shown = np.where(np.isfinite(v), v, 0.0)
        ax.bar(x + i * width, shown, width, color=colors[i], label=m)
        for xi, vi in zip(x, v, strict=True):
            if not np.isfinite(vi):
                ax.text(xi + i * width, 0.1, "never", rotation=90, fontsize=7, ha="center")
    ax.set_xticks(x + width * (len(metrics) - 1) / 2, ids, fontsize=8)
    ax.set_ylabel("scans")
    ax.set_title("Time to confirm: scans from a target's appearance to its first confirmed track")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    save_figure(fig, paths[4], dpi=110)
    plt.close(fig)
    return paths


def mc_figure(mc_dir: Path, doc: dict[str, Any]) -> Path:
    """``montecarlo.png`` of a surveillance ``covnet mc``: per metric the mean GOSPA and the
    mean number of confirmed tracks per scan, each with its 95 % interval over the seeds (the
    axes start at 0, as both quantities do: Student's interval of a few seeds reaches below)."""
    agg = doc["aggregate"]
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True, layout="constrained")
    for i, (m, b) in enumerate(agg.items()):
        col = plt.get_cmap("tab10")(i)
        for ax, key in zip(axes, ("gospa_per_scan", "n_confirmed_per_scan"), strict=True):
            s = b[key]
            k = np.arange(1, len(s["mean"]) + 1)
            ax.plot(k, s["mean"], color=col, lw=1.5, label=m)
            if s["ci95_low"] is not None:  # one seed: no interval
                ax.fill_between(k, s["ci95_low"], s["ci95_high"], color=col, alpha=0.2)
    for ax in axes:  # both are >= 0: a few seeds' t-interval may reach below (not drawn)
        ax.set_ylim(bottom=0.0)
    axes[0].set_ylabel("GOSPA (m)")
    axes[1].set_ylabel("confirmed tracks")
    axes[1].set_xlabel("scan k")
    axes[0].legend(fontsize=8)
    n = len(doc["seeds"])
    axes[0].set_title(f"{doc['scenario']}: means over {n} seeds with 95 % intervals")
    for ax in axes:
        ax.grid(alpha=0.3)
    path = mc_dir / "montecarlo.png"
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path
