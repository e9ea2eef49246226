"""``covnet compare``: the fusion structures side by side over a Monte Carlo batch.

For each fusion mode (``central``, ``info``, ``ci``, ``ci-fast``, ``peer-info``, ``peer-ci``; the
peer graph is the config's ``fusion.peer.graph`` unless ``--graph`` says otherwise) and each of
``R`` seeds, the in-process run of :mod:`covnet.covariance_control.decentral_sim` (the loops the
network processes run), then per mode:

- ``allocation_rate``: mean over runs of ``η = (1/(N Ns)) Σ_k N_k``;
- ``rmse_position``: sqrt of the mean over runs, scans and (peer) nodes of the squared position
  error;
- NEES: per scan the mean over runs ``ε̄_k`` (peer: each run's node-average), from scan
  ``skip+1`` on (``skip`` = 10, or half the run when it is shorter than 20 scans);
  ``R ε̄_k ~ χ²(R n)`` for a consistent filter, so the two-sided 95 % band is
  ``[χ²_{0.025}(R n) / R, χ²_{0.975}(R n) / R]``.  Reported: the fraction of scans inside that
  band, the grand mean over runs and scans with its 95 % confidence interval (Student t over the
  ``R`` run averages: scans within one run are correlated, runs are independent), and a verdict:
  ``consistent`` (the interval contains ``n = 4``), ``conservative`` (entirely below: the
  filter claims more uncertainty than it has, as covariance intersection does by design) or
  ``optimistic`` (entirely above: over-confident, the dangerous side);
- ``messages_per_scan`` / ``bytes_per_scan``: what the structure publishes per scan (truth
  and heartbeats excluded), counted by encoding the very messages of the wire schema
  (:mod:`covnet.wire.messages`): central — one command, the enabled sensors' measurements, the fused
  track and status; info/ci — the same with local tracks for measurements; peer — the enabled
  nodes' local tracks and every node's own track and status (``deliveries_per_scan`` counts each
  message once per process that receives it: a command goes to the sensors it enables and the
  recorder, a local track to each neighbour).

Runs are spread over processes (``spawn``; one per core by default) and are deterministic for a
seed, so the table is too.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import chi2

from covnet.batches.pool import BatchInterrupted, write_rows
from covnet.batches.stats import (
    CUT,
    SHARE,
    add_stats,
    burn_in_of,
    ci_half_width,
    count_range,
    curves_of,
    error_stats,
    seed_stats,
    t_half_width,
)
from covnet.batches.trials import (
    Batch,
    BatchProgress,
    Outcome,
    complete_points,
    run_trials,
    trial_hash,
)
from covnet.covariance_control.config import Scenario, from_dict, normalised
from covnet.covariance_control.decentral import neighbours
from covnet.covariance_control.decentral_sim import run_mode
from covnet.covariance_control.fusion_rules import FUSION_RULES, rule_for, track_rules
from covnet.covariance_control.model import build_model, truth_trajectory
from covnet.covariance_control.simulate import MetricRun
from covnet.covariance_control.sweep import _pm
from covnet.covariance_control.sweep import curves_figure as sweep_curves_figure
from covnet.runs.rundir import save_figure
from covnet.wire import messages as msg


def modes() -> tuple[str, ...]:
    """What ``covnet compare`` compares: every rule of the registry at a fusion centre,
    covariance intersection with the closed-form weights (``ci-fast``), every track rule in a
    peer network (``peer-<rule>``)."""
    return (*FUSION_RULES, "ci-fast", *(f"peer-{r}" for r in track_rules()))


def default_modes() -> tuple[str, ...]:
    """``covnet compare``'s default: every mode but ``ci-fast``."""
    return tuple(m for m in modes() if m != "ci-fast")


def scenario_for(
    sc: Scenario, mode: str, graph: str | None = None, seed: int | None = None
) -> Scenario:
    """``sc`` with the fusion structure of ``mode`` (and ``graph`` for the peer modes)."""
    if mode not in modes():
        raise ValueError(f"unknown fusion mode {mode!r}; choose from {list(modes())}")
    data = normalised(sc)
    fusion = dict(data["fusion"])
    peer = dict(fusion["peer"])
    if mode.startswith("peer-"):
        fusion["mode"] = "peer"
        peer["rule"] = mode.split("-", 1)[1]
    elif mode == "ci-fast":
        fusion.update(mode="ci", ci_objective="fast")
    else:
        fusion["mode"] = mode
    if graph is not None:
        peer["graph"] = graph
    fusion["peer"] = peer
    data["fusion"] = fusion
    if seed is not None:
        data["seed"] = seed
    return from_dict(data, f"{sc.name} ({mode})")


@dataclass(frozen=True)
class Trial:
    """One run's numbers: per scan NEES (node-averaged in peer mode), squared position error
    (node-averaged), sensors enabled."""

    mode: str
    seed: int
    nees: np.ndarray  # (N,)
    pos_err2: np.ndarray  # (N,)
    enabled: np.ndarray  # (N, Ns) bool

    def as_dict(self) -> dict[str, Any]:
        """The trial as JSON-able data (what the batch layer stores and sends)."""
        return {
            "mode": self.mode,
            "seed": self.seed,
            "nees_scan": np.asarray(self.nees, dtype=np.float64).tolist(),
            "pos_err2_scan": np.asarray(self.pos_err2, dtype=np.float64).tolist(),
            "enabled_scan": ["".join("1" if b else "0" for b in row) for row in self.enabled],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Trial:
        return cls(
            str(d["mode"]),
            int(d["seed"]),
            nees=np.asarray(d["nees_scan"], dtype=np.float64),
            pos_err2=np.asarray(d["pos_err2_scan"], dtype=np.float64),
            enabled=np.asarray([[c == "1" for c in row] for row in d["enabled_scan"]], dtype=bool),
        )


def run_trial(args: tuple[dict[str, Any], str, str | None, int, str]) -> Trial:
    """One (mode, seed) run; a top-level function so that worker processes can import it."""
    data, mode, graph, seed, metric = args
    sc = scenario_for(from_dict(data), mode, graph, seed)
    model = build_model(sc)
    truth = truth_trajectory(model)
    run, nodes = run_mode(sc, metric, model)
    runs: list[MetricRun] = list(nodes.values()) if nodes else [run]
    err = np.stack([r.x_est - truth for r in runs])  # (nodes, N, 4)
    return Trial(
        mode,
        seed,
        nees=np.mean([r.nees for r in runs], axis=0),
        pos_err2=np.mean(err[..., 0] ** 2 + err[..., 2] ** 2, axis=0),
        enabled=run.enabled,
    )


def run_seeds(task: tuple[dict[str, Any], str, str | None, list[int], str]) -> list[dict[str, Any]]:
    """The runs of one mode with each of ``seeds``, as data (a task of
    :mod:`covnet.batches.trials`)."""
    data, mode, graph, seeds, metric = task
    return [run_trial((data, mode, graph, s, metric)).as_dict() for s in seeds]


STAMP_NS = 1 << 45
"""The ``t_sent_ns`` of every message encoded to count bytes: a monotonic clock read more than
4.3 s after boot, as every real one is, which msgpack writes in 9 bytes (a placeholder of 1 took
one byte and left the count 7 % short of a recording's)."""


class SeqCounter:
    """The ``seq`` a sensor puts on each message it sends the centre (1, 2, ... per sensor), so an
    encoded placeholder is as long as the real one."""

    def __init__(self) -> None:
        self._n: dict[str, int] = {}

    def __call__(self, sensor_id: str) -> int:
        self._n[sensor_id] = n = self._n.get(sensor_id, 0) + 1
        return n


def traffic_per_scan(
    sc: Scenario, mode: str, enabled: np.ndarray, graph: str | None
) -> dict[str, float]:
    """Messages, bytes and deliveries published per scan by ``mode`` for the enabled sets
    ``enabled`` ``(N, Ns)`` (see the module docstring), from the encoded wire messages (each
    with the fields a real one has: a :data:`STAMP_NS` stamp, a sensor's ``seq`` to the
    centre; a peer node numbers nothing)."""
    ids = sc.sensor_ids
    x, P = np.zeros(4), np.eye(4)
    z, R = np.zeros((1, 2)), np.eye(2)
    msgs = byts = deliveries = 0
    seq, ns = SeqCounter(), STAMP_NS
    peer = mode.startswith("peer-")
    fusion = scenario_for(sc, mode, graph).fusion
    nbrs = neighbours(fusion, ids) if peer else {}
    tracks = rule_for(fusion).tracks
    for k, row in enumerate(enabled, start=1):
        on = tuple(ids[j] for j in np.flatnonzero(row))
        out: list[tuple[msg.Message, int]] = []  # (message, receivers)
        if peer:
            for j in np.flatnonzero(row):
                lt = msg.LocalTrack(ids[j], k, float(k), x, P, x, P, ns, 0)  # a peer's: no seq
                out.append((lt, len(nbrs[int(j)])))
            for i, sid in enumerate(ids):
                out.append((msg.Track(k, float(k), x, P, ns, 0, node_id=sid), 1))
                # a node fuses its own track and its neighbours' (sensors.peer)
                fused = tuple(ids[j] for j in np.flatnonzero(row) if j == i or j in nbrs[i])
                st = msg.Status(k, float(k), on, 1.0, 1.0, 1.0, ns, 0, fused=fused, node_id=sid)
                out.append((st, len(ids)))  # every other node and the monitor
        else:
            out.append((msg.Command(k, float(k), on, ns, 0), len(on) + 1))  # + the recorder
            for sid in on:
                if tracks:
                    out.append((msg.LocalTrack(sid, k, float(k), x, P, x, P, ns, 0, seq(sid)), 1))
                else:
                    out.append((msg.Measurement(sid, k, float(k), z, R, ns, 0, seq=seq(sid)), 1))
            out.append((msg.Track(k, float(k), x, P, ns, 0), 1))
            out.append((msg.Status(k, float(k), on, 1.0, 1.0, 1.0, ns, 0, fused=on), 1))
        for m, receivers in out:
            msgs += 1
            byts += len(msg.encode(m))
            deliveries += receivers
    n = max(len(enabled), 1)
    return {
        "messages_per_scan": msgs / n,
        "bytes_per_scan": byts / n,
        "deliveries_per_scan": deliveries / n,
    }


def nees_consistency(
    all_nees: np.ndarray, skip: int, dim: int = 4, per_scan: int = 1
) -> dict[str, Any]:
    """The NEES columns of a table row (see the module docstring) from per-seed, per-scan NEES
    ``all_nees`` ``(R, N)``, from scan ``skip + 1`` on; each value the average of ``per_scan``
    independent NEES of a ``dim``-state filter (many targets: the targets' average), so a
    consistent filter's ``R``-seed average of a scan is ``χ²(dim R per_scan) / (R per_scan)``:
    ``mean_nees``, ``nees_band_95``, ``nees_mean_ci_95``, ``nees_inside_fraction`` and
    ``nees_verdict`` (``consistent``, ``conservative`` or ``optimistic`` against ``dim``)."""
    R = all_nees.shape[0]
    n = R * per_scan
    nees = all_nees[:, skip:]
    per_scan_mean = nees.mean(axis=0)
    lo, hi = (float(v) for v in np.asarray(chi2.ppf([0.025, 0.975], dim * n)) / n)
    grand = float(per_scan_mean.mean())
    # the grand mean's 95 % confidence interval from the R independent run averages (scans
    # within a run are correlated, so they are not counted as independent samples)
    run_means = nees.mean(axis=1)
    half = float(t_half_width(run_means.std(ddof=1), R))
    glo, ghi = max(grand - half, 0.0), grand + half  # a NEES is >= 0 (as every batch interval)
    d = float(dim)
    verdict = "consistent" if glo <= d <= ghi else ("conservative" if ghi < d else "optimistic")
    return {
        "mean_nees": grand,
        "nees_band_95": [lo, hi],
        "nees_mean_ci_95": [glo, ghi],
        "nees_inside_fraction": float(np.mean((per_scan_mean >= lo) & (per_scan_mean <= hi))),
        "nees_verdict": verdict,
    }


def summarise(
    sc: Scenario,
    mode: str,
    trials: Sequence[Trial],
    graph: str | None,
    skip: int = 10,
    burn_in: int | None = None,
) -> dict[str, Any]:
    """One row of the comparison table (see the module docstring); the NEES columns from
    scan ``burn_in + 1`` on when a burn-in is given (``evaluation.burn_in_scans``: they
    started at scan 11 whatever it was, beside ``nees_steady_*`` from the burn-in), else
    ``skip + 1``."""
    R = len(trials)
    all_nees = np.stack([t.nees for t in trials])
    # a short run keeps its second half
    skip = burn_in_of(skip if burn_in is None else burn_in, all_nees.shape[1])
    enabled = np.stack([t.enabled for t in trials])
    row: dict[str, Any] = {
        "mode": mode,
        "graph": graph or sc.fusion.peer.graph if mode.startswith("peer-") else None,
        "runs": R,
        "allocation_rate": float(enabled.mean()),
        "sensors_per_scan": float(enabled.sum(axis=2).mean()),
        "rmse_position": float(np.sqrt(np.mean([t.pos_err2 for t in trials]))),
        **nees_consistency(all_nees, skip),
    }
    row.update(traffic_per_scan(sc, mode, trials[0].enabled, graph))
    # the statistics over seeds (after the columns above, which keep their values)
    error_stats(
        row,
        np.stack([t.pos_err2 for t in trials]),
        all_nees,
        sc.evaluation.burn_in_scans if burn_in is None else burn_in,
    )
    add_stats(row, "allocation_rate", [float(t.enabled.mean()) for t in trials], SHARE)
    return row


def trial_key(sc: Scenario, metric: str, graph: str | None) -> str:
    """The hash that keys the comparison's trials: the config without its seed and evaluation
    settings, the metric and the peer graph (a mode is a point: adding modes resumes)."""
    data = normalised(sc)
    data.pop("seed", None)
    data.pop("evaluation", None)
    return trial_hash("compare", {"config": data, "metric": metric, "graph": graph})


def compare(
    sc: Scenario,
    modes: Sequence[str],
    metric: str,
    runs: int,
    *,
    graph: str | None = None,
    workers: int | None = None,
    progress: BatchProgress | None = None,
    out: Path | None = None,
    cluster: str | None = None,
) -> list[dict[str, Any]]:
    """The comparison table: one row per mode, over seeds ``sc.seed .. sc.seed + runs - 1``."""
    return compare_outcome(
        sc, modes, metric, runs, graph=graph, workers=workers, progress=progress, out=out,
        cluster=cluster,
    )[0]  # fmt: skip


def compare_outcome(
    sc: Scenario,
    modes: Sequence[str],
    metric: str,
    runs: int,
    *,
    graph: str | None = None,
    workers: int | None = None,
    progress: BatchProgress | None = None,
    out: Path | None = None,
    cluster: str | None = None,
    ci_width: float | None = None,
    max_seeds: int | None = None,
) -> tuple[list[dict[str, Any]], Outcome]:
    """``(rows, outcome)``: the table and its trials (per mode in seed order), written to
    ``out`` as they finish and skipped when there (:func:`covnet.batches.trials.run_trials`)."""
    for m in modes:
        scenario_for(sc, m, graph)  # validates every mode (and the graph) before any work
    data = normalised(sc)
    burn = sc.evaluation.burn_in_scans

    def headline(mode: str, results: list[dict[str, Any]]) -> float:
        E = np.asarray([r["pos_err2_scan"] for r in results], dtype=np.float64)
        b = burn_in_of(burn, E.shape[1])
        return ci_half_width(seed_stats(np.sqrt(E[:, b:].mean(axis=1))))

    b = Batch(
        "compare",
        run_seeds,
        lambda mode, seeds: (data, mode, graph, seeds, metric),
        list(modes),
        first_seed=sc.seed,
        headline=headline,
        headline_name="steady-state RMSE (m)",
    )

    def rows_of(results: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
        return [
            summarise(sc, m, [Trial.from_dict(t) for t in results[m]], graph, burn_in=burn)
            for m in modes
            if m in results
        ]

    try:
        outcome = run_trials(
            b,
            runs,
            out=out,
            key=trial_key(sc, metric, graph) if out is not None else None,
            workers=workers,
            cluster=cluster,
            progress=progress,
            ci_width=ci_width,
            max_seeds=max_seeds,
        )
    except BatchInterrupted as stop:  # the modes with every seed
        stop.partial = rows_of(complete_points(b, stop.done, runs))
        raise
    return rows_of(outcome.results), outcome


def curves(results: dict[str, list[dict[str, Any]]]) -> dict[str, np.ndarray]:
    """The per-scan curves of every mode (:func:`covnet.batches.stats.curves_of`)."""
    return curves_of(results)


def default_curves(rows: Sequence[dict[str, Any]]) -> list[int]:
    """``curves.png`` shows every mode."""
    return list(range(len(rows)))


def curves_figure(out: Path, data: dict[str, np.ndarray], select: Sequence[int]) -> Path:
    """``curves.png``: per-scan RMSE and NEES of the modes ``select``, with their bands."""
    return sweep_curves_figure(out, data, select)


COLUMNS = (
    "mode",
    "graph",
    "runs",
    "allocation_rate",
    "sensors_per_scan",
    "rmse_position",
    "mean_nees",
    "nees_inside_fraction",
    "nees_verdict",
    "messages_per_scan",
    "bytes_per_scan",
    "deliveries_per_scan",
    "burn_in_scans",
    "rmse_steady",
    "rmse_steady_mean",
    "rmse_steady_std",
    "rmse_steady_ci_lo",
    "rmse_steady_ci_hi",
    "rmse_transient",
    "rmse_transient_max",
    "rmse_position_std",
    "rmse_position_ci_lo",
    "rmse_position_ci_hi",
    "nees_steady_mean",
    "nees_steady_ci_lo",
    "nees_steady_ci_hi",
    "allocation_rate_std",
    "allocation_rate_ci_lo",
    "allocation_rate_ci_hi",
)


def write_table(out: Path, rows: Sequence[dict[str, Any]], meta: dict[str, Any]) -> None:
    """``compare.json`` (rows and how they were made) and ``compare.csv``."""
    write_rows(out, "compare", rows, meta, COLUMNS)


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    head = (
        f"{'mode':>10} {'runs':>4} {'rate %':>7} {'RMSE m':>7} {'steady RMSE m':>13} "
        f"{'transient m':>11} {'NEES':>6} {'in band':>8} {'verdict':>12} "
        f"{'msgs/scan':>9} {'B/scan':>8}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        tr = r.get("rmse_transient")
        lines.append(
            f"{r['mode']:>10} {r['runs']:>4} {100 * r['allocation_rate']:7.1f} "
            f"{r['rmse_position']:7.2f} {_pm(r, 'rmse_steady'):>13} "
            f"{'-' if tr is None else f'{tr:.2f}':>11} "
            f"{r['mean_nees']:6.2f} {100 * r['nees_inside_fraction']:7.0f}% "
            f"{r['nees_verdict']:>12} "
            f"{r['messages_per_scan']:9.1f} {r['bytes_per_scan']:8.0f}"
        )
    lines.append(
        f"NEES: 'in band' = scans whose run-average is inside the 95 % chi-square band "
        f"{_bands(rows)}; 'verdict' = where the grand mean's 95 % "
        "confidence interval lies against 4 (the state dimension)"
    )
    if rows[0].get("burn_in_scans") is not None:
        lines.append(
            f"RMSE m: every scan; steady: after the first {rows[0]['burn_in_scans']} scans "
            "(evaluation.burn_in_scans), mean over seeds ± the half-width of its 95 % t "
            f"interval ({CUT}); transient: those first scans (pooled)"
        )
    return "\n".join(lines)


def _bands(rows: Sequence[dict[str, Any]]) -> str:
    """The chi-square bands of the rows' NEES, by their number of runs (the band of R runs'
    average depends on R: with ``--ci-width`` the modes run different counts, and the table
    gave the first mode's for all)."""
    by_runs = {int(r["runs"]): r["nees_band_95"] for r in rows}
    return ", ".join(f"[{lo:.2f}, {hi:.2f}] of {n} runs" for n, (lo, hi) in sorted(by_runs.items()))


def make_figure(out: Path, rows: Sequence[dict[str, Any]], title: str) -> Path:
    """``compare.png``: allocation rate, position RMSE, mean NEES (with the 95 % band) and
    bytes per scan, one bar per mode."""
    import matplotlib  # the figure only: start-up of the runs (and of the workers)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = [r["mode"] for r in rows]
    fig, axes = plt.subplots(1, 4, figsize=(15, 4.2))
    colors = plt.cm.tab10(np.arange(len(rows)))
    steady = [r.get("rmse_steady_mean", r["rmse_position"]) for r in rows]
    panels = (
        ("allocation rate [%]", [100 * r["allocation_rate"] for r in rows]),
        (f"position RMSE after {rows[0].get('burn_in_scans', 0)} scans [m]", steady),
        ("mean NEES (4 states)", [r["mean_nees"] for r in rows]),
        ("bytes published per scan", [r["bytes_per_scan"] for r in rows]),
    )
    for ax, (label, vals) in zip(axes, panels, strict=True):
        ax.bar(modes, vals, color=colors)
        ax.set_title(label)
        ax.tick_params(axis="x", rotation=35)
        ax.grid(axis="y", alpha=0.3)
    for ax, key, scale in ((axes[0], "allocation_rate", 100.0), (axes[1], "rmse_steady", 1.0)):
        if all(r.get(f"{key}_ci_lo") is not None for r in rows):
            m = np.array([r[f"{key}_mean"] for r in rows]) * scale
            lo_ = np.array([r[f"{key}_ci_lo"] for r in rows]) * scale
            hi_ = np.array([r[f"{key}_ci_hi"] for r in rows]) * scale
            ax.errorbar(modes, m, yerr=[m - lo_, hi_ - m], fmt="none", ecolor="k", capsize=4)
    ci = np.array([r["nees_mean_ci_95"] for r in rows]).T
    mean = np.array([r["mean_nees"] for r in rows])
    axes[2].errorbar(
        modes,
        mean,
        yerr=[mean - ci[0], ci[1] - mean],
        fmt="none",
        ecolor="k",
        capsize=4,
        label="95 % CI of the mean",
    )
    # each mode's band, of its own number of runs
    band = np.array([r["nees_band_95"] for r in rows], dtype=float)
    axes[2].bar(
        modes, band[:, 1] - band[:, 0], bottom=band[:, 0], width=0.95, color="0.6",
        alpha=0.35, zorder=0, label="95 % χ² band (per scan)",
    )  # fmt: skip
    axes[2].axhline(4.0, color="k", lw=0.8, ls="--")
    axes[2].legend(loc="upper right", fontsize=8)
    fig.suptitle(f"{title}, {count_range(r['runs'] for r in rows)} seeds a mode")
    fig.tight_layout()
    path = out / "compare.png"
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def figure_title(meta: Mapping[str, Any]) -> str:
    """``compare.png``'s title from the table's meta data (the command's, and ``covnet plot``'s
    when it redraws the figure from ``compare.json``)."""
    return (
        f"{meta.get('scenario', '')}: fusion structures, metric {meta.get('metric', '?')}, "
        f"peer graph {meta.get('graph', '?')}"
    )
