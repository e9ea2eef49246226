"""Figures of the passive association study, drawn from result files only (never re-running a
scan):

* ``fig_p_vs_d.png`` (from ``results.json``): correct-association rate p against the spacing d,
  one line per method, one panel per (σ, formation, clutter);
* ``fig_time.png`` (from ``results.json``): median time per scan per method, clutter off / on;
* ``scene.png`` (from ``association.json``): one scan in plan view: lines of sight, true
  targets, associated positions and ghosts (associated triples that are wrong), with a zoom on
  the formation.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from covnet.passive.montecarlo import trials_text, where_it_ran  # noqa: E402
from covnet.runs.rundir import save_figure  # noqa: E402

P_VS_D = "fig_p_vs_d.png"
TIME = "fig_time.png"
SCENE = "scene.png"

_METHOD_STYLE = {
    "cot": ("tab:blue", "o", "-"),
    "lr": ("tab:orange", "s", "--"),
    "milp": ("tab:green", "^", ":"),
    "greedy": ("tab:red", "v", "-."),
}
_SENSOR_COLORS = ("tab:purple", "tab:brown", "tab:cyan")


def _style(method: str, i: int) -> tuple[str, str, str]:
    if method in _METHOD_STYLE:
        return _METHOD_STYLE[method]
    return plt.get_cmap("tab10").colors[(i + 4) % 10], "D", "-"  # type: ignore[attr-defined]


def _trial_interval(row: dict[str, Any]) -> tuple[float, float, float]:
    """A row's per-trial share associated: its mean and 95 % interval, as ``results.json``
    has them (NaN without one).  The figure drew half the interval's width around the pooled
    ``p`` instead, which is not the interval of anything (the targets per trial vary)."""
    m, lo, hi = (row.get(f"p_trial_{k}") for k in ("mean", "ci_lo", "ci_hi"))
    if m is None or lo is None or hi is None:
        return (float("nan"),) * 3
    return float(m), float(lo), float(hi)


def mc_figures(out_dir: Path) -> list[Path]:
    """Draw ``fig_p_vs_d.png`` and ``fig_time.png`` from ``out_dir/results.json``."""
    doc = json.loads((out_dir / "results.json").read_text())
    rows: list[dict[str, Any]] = doc["rows"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    forms = list(dict.fromkeys(r["formation"] for r in rows))
    clutters = list(dict.fromkeys(r["clutter"] for r in rows))
    sigmas = sorted({r["sigma_mrad"] for r in rows})
    cols = [(f, c) for f in forms for c in clutters]
    paths = [out_dir / P_VS_D, out_dir / TIME]

    # p against d
    fig, axes = plt.subplots(
        len(sigmas),
        len(cols),
        figsize=(3.6 * len(cols) + 1.0, 2.9 * len(sigmas) + 0.9),
        squeeze=False,
        sharex=True,
        sharey=True,
        layout="constrained",
    )
    ps = [r["p"] for r in rows if r["p"] is not None]
    lo = max(0.0, min(ps) - 0.05) if ps else 0.0
    for a, s in enumerate(sigmas):
        for b, (f, c) in enumerate(cols):
            ax = axes[a, b]
            for i, m in enumerate(methods):
                sel = sorted(
                    (r["d_km"], np.nan if r["p"] is None else r["p"], *_trial_interval(r))
                    for r in rows
                    if r["method"] == m
                    and r["formation"] == f
                    and r["clutter"] == c
                    and r["sigma_mrad"] == s
                )
                if not sel:
                    continue
                color, marker, ls = _style(m, i)
                d, p, tm, tlo, thi = (np.asarray(v) for v in zip(*sel, strict=True))
                if np.any(np.isfinite(tm)):  # the per-trial mean and its 95 % interval
                    ax.errorbar(
                        d, tm, yerr=[tm - tlo, thi - tm], fmt="_", color=color, ms=8,
                        capsize=3, lw=1.0,
                    )  # fmt: skip
                hollow = m == "milp"
                ax.plot(
                    d,
                    p,
                    color=color,
                    marker=marker,
                    ls=ls,
                    lw=1.8,
                    ms=9 if hollow else 6,
                    mfc="none" if hollow else color,
                    mew=1.8,
                    label=m,
                )
            ax.set_title(f"{f}, clutter {'on' if c else 'off'}, σ = {s:g} mrad", fontsize=10)
            ax.grid(alpha=0.3)
            ax.set_ylim(lo, 1.01)
            if a == len(sigmas) - 1:
                ax.set_xlabel("target spacing d (km)")
            if b == 0:
                ax.set_ylabel("correct association rate p")
    ds = sorted({r["d_km"] for r in rows})
    for ax in axes[-1]:
        ax.set_xticks(ds)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=len(methods), fontsize=11)
    fig.suptitle(
        f"Passive association: correct association rate p against target spacing d "
        f"({trials_text(doc)} runs per cell; lr and milp usually coincide)\n"
        f"lines: p over every target of the cell's runs; bars: the per-run share's mean (tick) "
        f"and its 95 % interval",
        fontsize=12,
    )
    save_figure(fig, paths[0], dpi=110, bbox_inches="tight")
    plt.close(fig)

    # time per method
    fig, ax = plt.subplots(figsize=(9, 5.2), layout="constrained")
    width = 0.8 / max(1, len(clutters))
    x = np.arange(len(methods))
    all_t = [1e3 * r["median_time_s"] for r in rows]
    bottom = 0.3 * min(all_t)
    ax.set_yscale("log")
    ax.set_ylim(bottom, 3.0 * max(all_t))
    for j, c in enumerate(clutters):
        med, lo_e, hi_e = [], [], []
        for m in methods:
            t = np.array(
                [1e3 * r["median_time_s"] for r in rows if r["method"] == m and r["clutter"] == c]
            )
            med.append(float(np.median(t)))
            lo_e.append(float(np.median(t) - t.min()))
            hi_e.append(float(t.max() - np.median(t)))
        ref = med[methods.index("cot")] if "cot" in methods else None
        pos = x + (j - (len(clutters) - 1) / 2) * width
        ax.bar(
            pos,
            med,
            width * 0.95,
            yerr=[lo_e, hi_e],
            capsize=4,
            color="0.6" if c else "0.85",
            edgecolor="k",
            label=f"clutter {'on' if c else 'off'}",
        )
        for xp, v in zip(pos, med, strict=True):
            text = f"{v:.2f} ms" + (f"\n{v / ref:.1f}× cot" if ref and v != ref else "")
            ax.text(xp, np.sqrt(bottom * v), text, ha="center", va="center", fontsize=9)
    ax.set_xticks(x, methods)
    ax.set_ylabel("time per scan (ms, log scale)")
    ax.set_title(
        "Median time per scan over the grid cells (bars: median of cell medians; whiskers: "
        "min-max)\n" + where_it_ran(doc),
        fontsize=10,
    )
    ax.grid(alpha=0.3, axis="y", which="both")
    ax.legend()
    save_figure(fig, paths[1], dpi=110)
    plt.close(fig)
    return paths


def _draw_scene(
    ax: plt.Axes, doc: dict[str, Any], ray_km: float, label_targets: bool = False
) -> None:
    sensors = np.array([s["position_km"] for s in doc["sensors"]])
    for s, meas in enumerate(doc["measurements"]):
        color = _SENSOR_COLORS[s % 3]
        for z in meas:
            a = z["azimuth_rad"]
            end = sensors[s, :2] + ray_km * np.array([np.cos(a), np.sin(a)])
            ls = "-" if z["label"] >= 0 else (0, (4, 3))
            ax.plot(
                [sensors[s, 0], end[0]],
                [sensors[s, 1], end[1]],
                color=color,
                lw=0.9,
                ls=ls,
                alpha=0.75,
            )
        ax.plot(
            *sensors[s, :2],
            marker="*",
            ms=15,
            color=color,
            mec="k",
            ls="none",
            label=f"sensor {doc['sensors'][s]['id']} (its LOS; dashed: clutter)",
        )
    tg = np.array(doc["targets_km"])
    seen = np.zeros(len(tg), dtype=bool)
    seen[np.asarray(doc["truth_targets"], dtype=int)] = True
    ax.plot(
        tg[seen, 0],
        tg[seen, 1],
        "o",
        ms=11,
        mfc="none",
        mec="k",
        mew=1.8,
        label="true targets (seen by all three sensors)",
    )
    if (~seen).any():
        ax.plot(
            tg[~seen, 0],
            tg[~seen, 1],
            "o",
            ms=11,
            mfc="none",
            mec="0.5",
            mew=1.5,
            ls="none",
            label="true targets (missed by a sensor)",
        )
    if label_targets:
        for i, p in enumerate(tg):
            ax.annotate(
                f"T{i + 1}", (p[0], p[1]), xytext=(7, 7), textcoords="offset points", fontsize=9
            )
    pos = np.array(doc["positions_km"]).reshape(-1, 3)
    ok = np.array(doc["correct"], dtype=bool)
    if ok.any():
        ax.plot(
            pos[ok, 0],
            pos[ok, 1],
            "+",
            ms=12,
            mew=2.2,
            color="tab:green",
            label="associated (correct)",
        )
    if (~ok).any():
        ax.plot(
            pos[~ok, 0],
            pos[~ok, 1],
            "x",
            ms=11,
            mew=2.2,
            color="tab:red",
            label="ghost (wrong triple)",
        )


def scene_figure(out_dir: Path) -> Path:
    """Draw ``scene.png`` from ``out_dir/association.json``."""
    doc = json.loads((out_dir / "association.json").read_text())
    sensors = np.array([s["position_km"] for s in doc["sensors"]])
    tg = np.array(doc["targets_km"])
    pts = np.vstack([sensors[:, :2], tg[:, :2]])
    span = float(np.ptp(pts, axis=0).max())
    fig, axes = plt.subplots(1, 2, figsize=(14, 6.8), layout="constrained")
    for k, ax in enumerate(axes):
        _draw_scene(ax, doc, ray_km=3.0 * span, label_targets=k == 1)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        ax.set_xlabel("x east (km)")
        ax.set_ylabel("y north (km)")
        if k == 0:
            pad = 0.08 * span
            ax.set_xlim(pts[:, 0].min() - pad, pts[:, 0].max() + pad)
            ax.set_ylim(pts[:, 1].min() - pad, pts[:, 1].max() + pad)
            ax.set_title("Plan view: lines of sight of every measurement")
        else:
            c = tg[:, :2].mean(axis=0)
            half = 0.6 * float(np.ptp(tg[:, :2], axis=0).max()) + 0.5
            ax.set_xlim(c[0] - half, c[0] + half)
            ax.set_ylim(c[1] - half, c[1] + half)
            ax.set_title("Zoom on the formation")
            for p, good in zip(doc["positions_km"], doc["correct"], strict=True):
                if not good:
                    ax.annotate(
                        f"z = {p[2]:.2f} km",
                        (p[0], p[1]),
                        xytext=(6, -12),
                        textcoords="offset points",
                        fontsize=8,
                        color="tab:red",
                    )
    axes[0].legend(loc="upper right", fontsize=8, framealpha=0.9)
    s = doc["score"]
    fig.suptitle(
        f"{doc['method']} on "
        + (f"scan {doc['scan']} of a network run" if "scan" in doc else "one scan")
        + f" ({doc['formation']}, d = {doc['d_km']:g} km, "
        f"σ = {doc['sigma_azimuth_mrad']:g}/{doc['sigma_elevation_mrad']:g} mrad, clutter "
        f"{'on' if doc['clutter'] else 'off'}, seed {doc['seed']}): "
        f"{s['correct']} of the {s['truth']} targets seen by all three sensors associated, "
        f"{s['output'] - s['correct']} ghost(s)",
        fontsize=11,
    )
    path = out_dir / SCENE
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path
