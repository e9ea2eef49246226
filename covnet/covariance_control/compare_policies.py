"""``covnet compare CONFIG --policies a,b,...``: allocation policies side by side over seeds.

For each policy (``allocation.policy``, :data:`covnet.core.allocation.policy_registry.POLICIES`)
and each of ``R`` seeds — the same seeds for every policy, so the comparison is paired — the
in-process run of the config with that policy (and its budget ``K``;
:func:`covnet.covariance_control.simulate.run_metric`, many targets
:func:`~covnet.covariance_control.simulate.run_targets`), then per policy, each statistic over
the seeds with its 95 % Student t interval (:mod:`covnet.batches.stats`) and the seed count:

- **accuracy**: the position RMSE after ``evaluation.burn_in_scans`` (``rmse_steady``, as
  ``covnet compare --modes``; many targets: pooled over the targets), the mean NEES after the
  burn-in with its χ² consistency verdict
  (:func:`covnet.covariance_control.compare.nees_consistency`; many targets: the targets'
  average, each a 4-state filter), and with ``targets:`` the mean OSPA and GOSPA over the
  run's scans (the run summary's ``mean_ospa`` / ``mean_gospa``);
- **cost**: sensor-scans ``Σ_k |D_k|`` and the mean sensors per scan; messages and bytes
  published per scan, from the encoded wire messages (one target: the fusion centre's
  structure, :func:`covnet.covariance_control.compare.traffic_per_scan`; many targets: one
  command naming each enabled sensor's target and its clutter window, one measurement per
  enabled sensor with the returns of its dwell, one track per target and one status);
- **how closely P follows P_d**: the mean objective ``f`` (the run's ``value``: the
  covariance-control objective of the chosen subset, whatever the policy; many targets the
  weighted sum ``Σ_t w_t f_t``) and the share of scans with ``tr P_post ≤ tr P_d`` (many
  targets: of target-scans).

Budgets: ``--budget K`` gives every policy that takes one (a budget-needing policy, or one that
scores a reward or an information gain) ``K`` sensors per scan; ``--budget match`` first runs
``covariance_control`` over the seeds and gives them ``K = round(mean sensors per scan)`` of it
("the same number of sensors": like for like); without ``--budget`` a policy takes the
config's ``allocation.budget`` (or ``max_active``), and one that needs a budget and has none
is refused.

Trials are the batch layer's (:mod:`covnet.batches.trials`): a policy with its budget is a
point (``policy=random,budget=5``), so adding a policy, or changing the budget, resumes the
rest.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from covnet.batches.pool import BatchInterrupted, write_rows
from covnet.batches.stats import (
    CUT,
    NONNEGATIVE,
    SHARE,
    add_stats,
    burn_in_of,
    ci_half_width,
    curves_of,
    error_stats,
    plus_minus,
    seed_stats,
    t_half_width,
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
from covnet.core.allocation.policy_registry import POLICIES, Policy
from covnet.covariance_control.compare import (
    STAMP_NS,
    SeqCounter,
    nees_consistency,
    traffic_per_scan,
)
from covnet.covariance_control.config import Scenario, from_dict, normalised
from covnet.covariance_control.fusion_rules import rule_for
from covnet.errors import UsageError
from covnet.runs.rundir import save_figure
from covnet.wire import messages as msg

MATCH = "match"
"""``--budget match``: the baselines get covariance control's mean sensors per scan."""
REFERENCE = "covariance_control"


def takes_budget(pol: Policy) -> bool:
    """A policy ``--budget`` applies to: one that needs a budget, or one that maximises a reward
    or an information gain (given the same ``K`` so that the comparison is like for like)."""
    return pol.needs_budget or pol.reward is not None


def parse_policies(text: str) -> list[str]:
    """``--policies a,b,...``: known names, at least one, no repeats."""
    names = [p.strip() for p in text.split(",") if p.strip()]
    if not names:
        raise UsageError("--policies: name at least one policy")
    for p in names:
        if p not in POLICIES:
            raise UsageError(f"--policies: unknown policy {p!r}; choose from {', '.join(POLICIES)}")
    dup = sorted({p for p in names if names.count(p) > 1})
    if dup:
        raise UsageError(f"--policies: {', '.join(dup)} named twice")
    return names


def parse_budget(text: str | None) -> int | str | None:
    """``--budget K|match``."""
    if text is None:
        return None
    if text.strip() == MATCH:
        return MATCH
    try:
        k = int(text)
    except ValueError:
        raise UsageError(f"--budget: a number of sensors K >= 1 or 'match', got {text!r}") from None
    if k < 1:
        raise UsageError(f"--budget: a number of sensors K >= 1 or 'match', got {k}")
    return k


def config_budget(sc: Scenario) -> int | None:
    """The budget a baseline takes from the config: ``allocation.budget``, else
    ``max_active``."""
    al = sc.allocation
    return al.budget if al.budget is not None else al.max_active


def budget_for(sc: Scenario, policy: str, budget: int | str | None) -> int | None:
    """The ``allocation.budget`` policy ``policy`` runs with: ``budget`` (a number) when it takes
    one, else the config's; ``None`` for a policy that takes none.  A policy that needs a budget
    and gets none is a :class:`~covnet.errors.UsageError` naming it."""
    pol = POLICIES[policy]
    if not takes_budget(pol):
        return None
    if isinstance(budget, int):
        return budget
    k = sc.allocation.budget
    if pol.needs_budget and k is None and sc.allocation.max_active is None:
        match = (
            ""  # a surveillance comparison refuses match: no advice it would refuse
            if sc.surveillance is not None
            else ", or --budget match (covariance control's mean sensors per scan)"
        )
        raise UsageError(
            f"--policies: {policy} ({pol.summary}) needs a budget K and {sc.name} has none "
            f"(allocation.budget or max_active): give --budget K{match}"
        )
    return k


def scenario_for(
    sc: Scenario, policy: str, budget: int | None, seed: int | None = None
) -> Scenario:
    """``sc`` with ``allocation.policy`` ``policy`` and ``allocation.budget`` ``budget`` (a config
    problem, e.g. a fusion rule a baseline cannot score, is a
    :class:`~covnet.errors.UsageError` naming the policy)."""
    data = normalised(sc)
    data["allocation"] = {**data["allocation"], "policy": policy, "budget": budget}
    if policy != REFERENCE:  # a baseline does not search the subsets: the search keys go
        for key in ("search", "gap", "time_limit_s", "node_limit"):
            data["allocation"].pop(key, None)
    if seed is not None:
        data["seed"] = seed
    try:
        return from_dict(data, f"{sc.name} with allocation.policy {policy}")
    except ConfigError as exc:
        problems = "; ".join(f"{path}: {text}" if path else text for path, text in exc.problems)
        raise UsageError(f"--policies: {policy} cannot run {sc.name}: {problems}") from None


def point_of(policy: str, budget: int | None) -> str:
    """The trial point of ``policy`` with ``budget``: ``policy=random,budget=5``."""
    p: dict[str, Any] = {"policy": policy}
    if budget is not None:
        p["budget"] = budget
    return point_key(p)


def trial_key(sc: Scenario, metric: str) -> str:
    """The hash that keys the trials: the config without its seed, its evaluation settings and
    its policy and budget (those are the points: adding a policy resumes), and the metric."""
    data = normalised(sc)
    data.pop("seed", None)
    data.pop("evaluation", None)
    data["allocation"] = {
        k: v for k, v in data["allocation"].items() if k not in ("policy", "budget")
    }
    return trial_hash("compare-policies", {"config": data, "metric": metric})


# --------------------------------------------------------------------------------------------
# one trial
# --------------------------------------------------------------------------------------------


def run_trial(data: Mapping[str, Any], policy: str, budget: int | None, seed: int, metric: str
              ) -> dict[str, Any]:  # fmt: skip
    """One (policy, seed) run, as the JSON-able data the batch layer stores: per scan the
    squared position error, NEES, sensors on, ``f`` and whether ``tr P ≤ tr P_d`` (many targets:
    the targets' averages and share, OSPA and GOSPA), and the run's traffic per scan."""
    sc = scenario_for(from_dict(dict(data)), policy, budget, seed)
    out: dict[str, Any] = {"policy": policy, "budget": budget, "seed": seed}
    if sc.multitarget:
        out.update(_targets_trial(sc, metric))
    else:
        out.update(_one_target_trial(sc, metric))
    return out


def _one_target_trial(sc: Scenario, metric: str) -> dict[str, Any]:
    from covnet.covariance_control.model import build_model  # start-up: the workers
    from covnet.covariance_control.simulate import run_metric, shared_trajectory

    model = build_model(sc)
    traj = shared_trajectory(model)
    run = run_metric(sc, metric, model)
    err = run.x_est - traj.truth
    trP = np.trace(run.P_post, axis1=1, axis2=2)
    trPd = np.trace(traj.P_d, axis1=1, axis2=2)
    traffic = traffic_per_scan(sc, sc.fusion.mode, run.enabled, None)
    return {
        "targets": 1,
        "pos_err2_scan": (err[:, 0] ** 2 + err[:, 2] ** 2).tolist(),
        "nees_scan": run.nees.tolist(),
        "sensors_scan": run.enabled.sum(axis=1).astype(int).tolist(),
        "value_scan": run.value.tolist(),
        "within_scan": (trP <= trPd).astype(float).tolist(),
        "messages_per_scan": traffic["messages_per_scan"],
        "bytes_per_scan": traffic["bytes_per_scan"],
    }


def _targets_trial(sc: Scenario, metric: str) -> dict[str, Any]:
    from covnet.covariance_control import targets  # start-up: the workers
    from covnet.covariance_control.results import ospa_series, target_trajectory
    from covnet.covariance_control.simulate import run_targets

    tm = targets.build(sc)
    traj = target_trajectory(tm)
    run = run_targets(sc, metric, tm)
    K = run.assignment.shape[0]
    truth = traj["truth"][:, :K]
    err = run.x_est - truth  # (T, K, 4)
    o, g = ospa_series(run, truth, tm.ospa_c, tm.ospa_p)
    trP = np.trace(run.P_post, axis1=2, axis2=3)  # (T, K)
    trPd = np.trace(traj["P_d"][:, :K], axis1=2, axis2=3)
    tracks = rule_for(sc.fusion).tracks  # info: each sensor sends its local track
    traffic = targets_traffic_per_scan(tm, run.assignment, run.returns, tracks)
    return {
        "targets": len(tm.target_ids),
        "pos_err2_scan": (err[..., 0] ** 2 + err[..., 2] ** 2).mean(axis=0).tolist(),
        "nees_scan": run.nees.mean(axis=0).tolist(),
        "sensors_scan": run.enabled.sum(axis=1).astype(int).tolist(),
        "value_scan": run.value.tolist(),
        "within_scan": (trP <= trPd).mean(axis=0).tolist(),
        "ospa_scan": o.tolist(),
        "gospa_scan": g.tolist(),
        # targets whose estimate was ever further from the truth than the OSPA cut-off
        "lost_tracks": int((np.hypot(err[..., 0], err[..., 2]).max(axis=1) > tm.ospa_c).sum()),
        **traffic,
    }


def targets_traffic_per_scan(
    tm: Any, assignment: np.ndarray, returns: np.ndarray, tracks: bool = False
) -> dict[str, float]:
    """Messages and bytes the many-target centre's structure publishes per scan for the
    assignments ``(K, N)`` (target index, ``-1`` off) and returns per dwell ``(K, N)``, from the
    encoded wire messages: a command (each enabled sensor's target and clutter window), a
    measurement per enabled sensor (its returns) or, under a track rule (``tracks``:
    ``fusion.mode: info``), its local track of the target it dwelt on (what
    :mod:`sensors.covariance` sends instead: posterior and prior, whatever its returns), a
    track per target and a status.  (The info form's bytes were counted as measurements':
    2.3 times fewer than the network sent.)"""
    ids, tids = tm.sensor_ids, tm.target_ids
    x, P = np.zeros(4), np.eye(4)
    msgs = byts = 0
    seq, ns = SeqCounter(), STAMP_NS  # the fields a real message has (compare.STAMP_NS)
    for k, row in enumerate(assignment, start=1):
        on = tuple(ids[j] for j in np.flatnonzero(row >= 0))
        who: dict[str, tuple[str, ...]] = {
            str(ids[j]): (str(tids[int(row[j])]),) for j in np.flatnonzero(row >= 0)
        }
        windows = {ids[j]: np.zeros(2 * tm.sensors[j].dim_z) for j in np.flatnonzero(row >= 0)}
        out: list[msg.Message] = [msg.Command(k, float(k), on, ns, 0, targets=who, windows=windows)]
        for j in np.flatnonzero(row >= 0):
            if tracks:
                tid = str(tids[int(row[j])])
                out.append(
                    msg.LocalTrack(
                        ids[j], k, float(k), x, P, x, P, ns, 0, seq(ids[j]), target_id=tid
                    )
                )
                continue
            dz = tm.sensors[j].dim_z
            m = max(int(returns[k - 1, j]), 0)
            out.append(
                msg.Measurement(
                    ids[j], k, float(k), np.zeros((m, dz)), np.eye(dz), ns, 0, seq=seq(ids[j])
                )
            )
        for tid in tids:
            out.append(msg.Track(k, float(k), x, P, ns, 0, target_id=tid))
        out.append(msg.Status(k, float(k), on, 1.0, 1.0, 1.0, ns, 0, fused=on))
        msgs += len(out)
        byts += sum(len(msg.encode(m_)) for m_ in out)
    n = max(len(assignment), 1)
    return {"messages_per_scan": msgs / n, "bytes_per_scan": byts / n}


def run_seeds(task: tuple[dict[str, Any], str, int | None, list[int], str]) -> list[dict[str, Any]]:
    """The runs of one policy with each of ``seeds`` (a task of :mod:`covnet.batches.trials`)."""
    data, policy, budget, seeds, metric = task
    return [run_trial(data, policy, budget, s, metric) for s in seeds]


# --------------------------------------------------------------------------------------------
# the table
# --------------------------------------------------------------------------------------------


def _stack(trials: Sequence[Mapping[str, Any]], name: str) -> np.ndarray:
    return np.asarray([t[name] for t in trials], dtype=np.float64)


def summarise(
    policy: str,
    budget: int | None,
    trials: Sequence[Mapping[str, Any]],
    burn_in: int,
    budget_source: str | None = None,
) -> dict[str, Any]:
    """One row of the table (see the module docstring)."""
    R = len(trials)
    err2 = _stack(trials, "pos_err2_scan")
    nees = _stack(trials, "nees_scan")
    sensors = _stack(trials, "sensors_scan")
    T = int(trials[0]["targets"])
    b = burn_in_of(burn_in, err2.shape[1])
    row: dict[str, Any] = {
        "policy": policy,
        "budget": budget,
        "budget_source": budget_source if budget is not None else None,
        "runs": R,
        "seeds": [int(t["seed"]) for t in trials],
        "targets": T,
        "sensors_per_scan": float(sensors.mean()),
        "sensor_scans": float(sensors.sum(axis=1).mean()),
        "rmse_position": float(np.sqrt(err2.mean())),
        **nees_consistency(nees, b, per_scan=T),
    }
    add_stats(row, "sensors_per_scan", sensors.mean(axis=1), NONNEGATIVE)
    add_stats(row, "sensor_scans", sensors.sum(axis=1), NONNEGATIVE)
    error_stats(row, err2, nees, burn_in)
    if "ospa_scan" in trials[0]:
        for name in ("ospa", "gospa"):
            per_seed = _stack(trials, f"{name}_scan").mean(axis=1)
            row[f"mean_{name}"] = float(per_seed.mean())
            add_stats(row, f"mean_{name}", per_seed, NONNEGATIVE)
        lost = [int(t.get("lost_tracks", 0)) for t in trials]
        row["seeds_with_lost_track"] = int(sum(n > 0 for n in lost))
        row["lost_tracks"] = int(sum(lost))
    f = _stack(trials, "value_scan").mean(axis=1)
    row["mean_f"] = float(f.mean())
    add_stats(row, "mean_f", f, NONNEGATIVE)  # f is a distance: every metric is >= 0
    share = _stack(trials, "within_scan").mean(axis=1)
    row["share_trP_le_trPd"] = float(share.mean())
    add_stats(row, "share_trP_le_trPd", share, SHARE)
    for name in ("messages_per_scan", "bytes_per_scan"):
        v = np.asarray([t[name] for t in trials], dtype=np.float64)
        row[name] = float(v.mean())
        add_stats(row, name, v, NONNEGATIVE)
    return row


@dataclass(frozen=True)
class Plan:
    """What runs: each policy's point and budget, and where the budget came from."""

    policies: tuple[str, ...]
    budgets: dict[str, int | None]
    source: str | None  # "match", "given", "config" or None
    matched: dict[str, Any] | None = None  # --budget match: K and what it was computed from

    def point(self, policy: str) -> str:
        return point_of(policy, self.budgets[policy])

    def source_of(self, policy: str) -> str | None:
        if self.budgets[policy] is None:
            return None
        if self.source in (MATCH, "given"):
            return self.source
        return "config"


def check(sc: Scenario, policies: Sequence[str], budget: int | str | None) -> None:
    """Every policy's scenario is valid (with a placeholder ``K`` for ``match``), before any
    work: a refusal names the policy."""
    probe = 1 if budget == MATCH else budget
    for p in policies:
        scenario_for(sc, p, budget_for(sc, p, probe))


def compare_outcome(
    sc: Scenario,
    policies: Sequence[str],
    metric: str,
    runs: int,
    *,
    budget: int | str | None = None,
    workers: int | None = None,
    progress: BatchProgress | None = None,
    out: Path | None = None,
    cluster: str | None = None,
) -> tuple[list[dict[str, Any]], Outcome, Plan]:
    """``(rows, outcome, plan)``: the table (one row per policy, in the order given), the
    trials (per point in seed order) and what ran; with ``budget`` ``match`` covariance control
    runs first (its trials are the same points: they are not run twice)."""
    check(sc, policies, budget)
    data = normalised(sc)
    burn = sc.evaluation.burn_in_scans
    key = trial_key(sc, metric) if out is not None else None
    done: dict[str, list[dict[str, Any]]] = {}
    ran = skipped = 0
    wall = 0.0
    backend: dict[str, Any] = {}

    def batch(points: dict[str, tuple[str, int | None]]) -> Batch:
        return Batch(
            "compare",
            run_seeds,
            lambda point, seeds: (data, *points[point], seeds, metric),
            list(points),
            first_seed=sc.seed,
            headline=_headline(burn),
            headline_name="steady-state RMSE (m)",
        )

    def run(points: dict[str, tuple[str, int | None]], plan: Plan | None) -> None:
        nonlocal ran, skipped, wall, backend
        b = batch(points)
        try:
            oc = run_trials(
                b, runs, out=out, key=key, workers=workers, cluster=cluster, progress=progress
            )
        except BatchInterrupted as stop:  # the policies with every seed
            if plan is not None:
                have = {**done, **complete_points(b, stop.done, runs)}
                stop.partial = _rows(plan, have, burn)
            raise
        done.update(oc.results)
        ran, skipped, wall = ran + oc.ran, skipped + oc.skipped, wall + oc.wall_s
        backend = oc.backend

    matched = None
    if budget == MATCH:
        ref = point_of(REFERENCE, None)
        run({ref: (REFERENCE, None)}, None)
        per_seed = [float(np.mean(t["sensors_scan"])) for t in done[ref]]
        k = max(1, int(round(float(np.mean(per_seed)))))
        matched = {
            "K": k,
            "from": REFERENCE,
            "mean_sensors_per_scan": float(np.mean(per_seed)),
            "seeds": len(per_seed),
        }
        budget_value: int | str | None = k
    else:
        budget_value = budget
    budgets = {p: budget_for(sc, p, budget_value) for p in policies}
    source = MATCH if budget == MATCH else "given" if isinstance(budget, int) else "config"
    plan = Plan(tuple(policies), budgets, source, matched)
    for p in policies:
        scenario_for(sc, p, budgets[p])  # the matched K too
    # the reference's trials of --budget match are done already (not run, nor counted, twice)
    points = {plan.point(p): (p, budgets[p]) for p in policies if plan.point(p) not in done}
    if points:
        run(points, plan)
    outcome = Outcome(
        {plan.point(p): done[plan.point(p)] for p in policies},
        {plan.point(p): runs for p in policies},
        ran=ran,
        skipped=skipped,
        wall_s=wall,
        backend=backend,
    )
    return _rows(plan, outcome.results, burn), outcome, plan


def _headline(burn: int) -> Any:
    def headline(point: str, results: list[dict[str, Any]]) -> float:
        E = np.asarray([r["pos_err2_scan"] for r in results], dtype=np.float64)
        b = burn_in_of(burn, E.shape[1])
        return ci_half_width(seed_stats(np.sqrt(E[:, b:].mean(axis=1))))

    return headline


def _rows(
    plan: Plan, results: Mapping[str, list[dict[str, Any]]], burn: int
) -> list[dict[str, Any]]:
    rows = [
        summarise(p, plan.budgets[p], results[plan.point(p)], burn, plan.source_of(p))
        for p in plan.policies
        if plan.point(p) in results
    ]
    ref = plan.point(REFERENCE) if REFERENCE in plan.policies else None
    if ref is not None and ref in results:
        for row in rows:
            if row["policy"] != REFERENCE:
                paired(row, results[plan.point(row["policy"])], results[ref], burn)
    return rows


def _accuracy(trials: Sequence[Mapping[str, Any]], burn_in: int) -> tuple[str, np.ndarray]:
    """The table's accuracy column per seed: the mean OSPA with targets, else the steady RMSE
    (as :func:`summarise` and :func:`covnet.batches.stats.error_stats` compute them)."""
    if "ospa_scan" in trials[0]:
        return "mean_ospa", _stack(trials, "ospa_scan").mean(axis=1)
    err2 = _stack(trials, "pos_err2_scan")
    return "rmse_steady", np.sqrt(err2[:, burn_in_of(burn_in, err2.shape[1]) :].mean(axis=1))


def paired(
    row: dict[str, Any],
    trials: Sequence[Mapping[str, Any]],
    ref: Sequence[Mapping[str, Any]],
    burn_in: int,
) -> None:
    """Add to ``row`` the paired differences from :data:`REFERENCE` over the seeds both ran
    (the same seeds: a policy's seed ``s`` and the reference's see the same target and
    noise), per seed ``d_s = a_s(policy) - a_s(reference)``, and their mean with its 95 % t
    interval, for the accuracy column (``<acc>_vs_reference_mean/std/ci_lo/ci_hi``) and the
    sensors per scan (``sensors_per_scan_vs_reference_...``).  Paired, a difference is
    resolved when its interval excludes 0, which two overlapping intervals of the rows do not
    decide either way."""
    mine = {int(t["seed"]): i for i, t in enumerate(trials)}
    common = [j for j, t in enumerate(ref) if int(t["seed"]) in mine]
    a = [trials[mine[int(ref[j]["seed"])]] for j in common]
    b = [ref[j] for j in common]
    if not a:
        return
    name, x = _accuracy(a, burn_in)
    _, y = _accuracy(b, burn_in)
    row["vs_reference"] = REFERENCE
    add_stats(row, f"{name}_vs_reference", x - y)
    on_a = _stack(a, "sensors_scan").mean(axis=1)
    on_b = _stack(b, "sensors_scan").mean(axis=1)
    add_stats(row, "sensors_per_scan_vs_reference", on_a - on_b)


# --------------------------------------------------------------------------------------------
# files, printout, figures
# --------------------------------------------------------------------------------------------


def _band(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-scan mean over seeds of ``values`` ``(R, N)`` with its 95 % t interval."""
    mean = values.mean(axis=0)
    R = values.shape[0]
    half = t_half_width(values.std(axis=0, ddof=1), R) if R >= 2 else np.full_like(mean, np.nan)
    return mean, mean - half, mean + half


def curves(results: Mapping[str, Sequence[Mapping[str, Any]]]) -> dict[str, np.ndarray]:
    """Per point the per-scan curves (:func:`covnet.batches.stats.curves_of`: RMSE and NEES
    with their bands) and the sensors on (``sensors``, ``sensors_lo``, ``sensors_hi``), with
    targets the OSPA (``ospa`` ...)."""
    out = curves_of(results)
    keys = [str(k) for k in out["points"]]
    names = ["sensors"]
    if keys and "ospa_scan" in results[keys[0]][0]:
        names.append("ospa")
    for name in names:
        bands = [_band(_stack(results[k], f"{name}_scan")) for k in keys]
        for i, suffix in enumerate(("", "_lo", "_hi")):
            out[f"{name}{suffix}"] = np.stack([bd[i] for bd in bands])
    return out


def default_curves(rows: Sequence[dict[str, Any]]) -> list[int]:
    """``curves.png`` shows every policy."""
    return list(range(len(rows)))


COLUMNS = (
    "policy",
    "budget",
    "budget_source",
    "runs",
    "sensors_per_scan",
    "sensors_per_scan_ci_lo",
    "sensors_per_scan_ci_hi",
    "sensor_scans",
    "sensor_scans_ci_lo",
    "sensor_scans_ci_hi",
    "burn_in_scans",
    "rmse_steady",
    "rmse_steady_mean",
    "rmse_steady_ci_lo",
    "rmse_steady_ci_hi",
    "rmse_position",
    "mean_nees",
    "nees_steady_ci_lo",
    "nees_steady_ci_hi",
    "nees_inside_fraction",
    "nees_verdict",
    "mean_ospa",
    "mean_ospa_ci_lo",
    "mean_ospa_ci_hi",
    "mean_gospa",
    "mean_gospa_ci_lo",
    "mean_gospa_ci_hi",
    "seeds_with_lost_track",
    "lost_tracks",
    "mean_f",
    "mean_f_ci_lo",
    "mean_f_ci_hi",
    "share_trP_le_trPd",
    "share_trP_le_trPd_ci_lo",
    "share_trP_le_trPd_ci_hi",
    "messages_per_scan",
    "messages_per_scan_ci_lo",
    "messages_per_scan_ci_hi",
    "bytes_per_scan",
    "bytes_per_scan_ci_lo",
    "bytes_per_scan_ci_hi",
    "vs_reference",
    *(
        f"{name}_vs_reference_{s}"
        for name in ("rmse_steady", "mean_ospa", "sensors_per_scan")
        for s in ("mean", "ci_lo", "ci_hi")
    ),
)


def write_table(out: Path, rows: Sequence[dict[str, Any]], meta: dict[str, Any]) -> None:
    """``compare.json`` (rows and how they were made) and ``compare.csv``."""
    write_rows(out, "compare", rows, meta, COLUMNS)


def _ci(r: Mapping[str, Any], name: str, fmt: str = ".2f", scale: float = 1.0) -> str:
    m = r.get(f"{name}_mean")
    if m is None:
        return "-"
    lo, hi = r.get(f"{name}_ci_lo"), r.get(f"{name}_ci_hi")
    return plus_minus(
        scale * m, None if lo is None else scale * lo, None if hi is None else scale * hi, fmt
    )


def _signed(r: Mapping[str, Any], name: str) -> str:
    """``+0.31 [+0.12, +0.49]`` of a paired difference (``=`` appended where its interval
    contains 0)."""
    m, lo, hi = (r.get(f"{name}_{k}") for k in ("mean", "ci_lo", "ci_hi"))
    if m is None:
        return "-"
    if lo is None or hi is None:
        return f"{m:+.2f}"
    return f"{m:+.2f} [{lo:+.2f}, {hi:+.2f}]" + (" =" if lo <= 0.0 <= hi else "")


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    many = any(r.get("mean_ospa") is not None for r in rows)
    acc = "mean OSPA m" if many else "RMSE m"
    head = (
        f"{'policy':>18} {'K':>5} {'seeds':>5} {'sensors/scan':>13} {acc:>14} "
        f"{'NEES':>5} {'verdict':>12} {'mean f':>16} {'trP<=trPd %':>12} "
        f"{'msgs/scan':>9} {'B/scan':>7}"
    )
    if many:
        head += f" {'lost':>5}"
    lines = [head, "-" * len(head)]
    for r in rows:
        k = (
            "-"
            if r["budget"] is None
            else f"{r['budget']}" + ("*" if r["budget_source"] == MATCH else "")
        )
        lines.append(
            f"{r['policy']:>18} {k:>5} {r['runs']:>5} {_ci(r, 'sensors_per_scan'):>13} "
            f"{_ci(r, 'mean_ospa' if many else 'rmse_steady'):>14} "
            f"{r['mean_nees']:5.2f} {r['nees_verdict']:>12} "
            f"{_ci(r, 'mean_f', '.3g'):>16} {_ci(r, 'share_trP_le_trPd', '.0f', 100.0):>12} "
            f"{r['messages_per_scan']:9.1f} {r['bytes_per_scan']:7.0f}"
            + (f" {r['seeds_with_lost_track']:>5}" if many else "")
        )
    versus = [r for r in rows if r.get("vs_reference")]
    if versus:
        lines.append(
            f"paired against {REFERENCE} (the same seeds; mean difference and its 95 % t "
            "interval; '=' where the interval contains 0: no difference shown):"
        )
        name = "mean_ospa" if many else "rmse_steady"
        for r in versus:
            lines.append(
                f"{r['policy']:>18}  {acc} {_signed(r, f'{name}_vs_reference')}, "
                f"sensors/scan {_signed(r, 'sensors_per_scan_vs_reference')}"
            )
    r0 = rows[0]
    if any(r["budget_source"] == MATCH for r in rows):
        lines.append(
            "K*: matched to covariance control's mean sensors per scan (--budget match), the "
            "same for every policy that takes a budget"
        )
    lines.append(
        f"each: mean over {r0['runs']} paired seeds ± the half-width of its 95 % t interval "
        f"({CUT}); "
        + (
            "mean OSPA over every scan"
            if many
            else f"RMSE after the first {r0['burn_in_scans']} scans (evaluation.burn_in_scans)"
        )
        + (f"; NEES after the first {r0['burn_in_scans']} scans" if many else "; NEES after them")
        + ", verdict: where its 95 % interval lies against 4; f: the "
        "covariance-control objective of the chosen subset; trP<=trPd: share of scans"
        + (
            " (target-scans); lost: seeds in which some track was ever further from its "
            "target than the OSPA cut-off"
            if many
            else ""
        )
    )
    return "\n".join(lines)


def _colors(n: int) -> Any:
    import matplotlib.pyplot as plt  # the figures only: start-up of the runs (and the workers)

    return plt.cm.tab10(np.arange(n) % 10)


def _err(r: Mapping[str, Any], name: str, m: float) -> Any:
    """An error bar's ``[[below], [above]]`` from a row's 95 % interval of ``name``."""
    lo, hi = r.get(f"{name}_ci_lo"), r.get(f"{name}_ci_hi")
    return None if lo is None or hi is None else [[m - lo], [hi - m]]


def make_figure(out: Path, rows: Sequence[dict[str, Any]], title: str) -> Path:
    """``pareto.png``: accuracy (steady RMSE, or mean OSPA with targets) against sensor-scans
    per scan (mean sensors per scan), one point per policy with its 95 % intervals in both
    axes."""
    import matplotlib  # the figure only: start-up of the runs (and of the workers)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    many = any(r.get("mean_ospa") is not None for r in rows)
    ykey = "mean_ospa" if many else "rmse_steady"
    fig, ax = plt.subplots(figsize=(7.5, 5.2))
    labels = []
    for r, c in zip(rows, _colors(len(rows)), strict=True):
        x, y = float(r["sensors_per_scan_mean"]), float(r[f"{ykey}_mean"])
        xerr, yerr = _err(r, "sensors_per_scan", x), _err(r, ykey, y)
        ax.errorbar([x], [y], xerr=xerr, yerr=yerr, fmt="o", color=c, capsize=4, ms=6)
        label = r["policy"] + ("" if r["budget"] is None else f" (K={r['budget']})")
        labels.append(
            ax.annotate(
                label, (x, y), textcoords="offset points", xytext=(6, 6), fontsize=8, color=c
            )  # fmt: skip
        )
    ax.margins(x=0.15, y=0.1)
    ax.set_xlabel("sensor-scans per scan (mean sensors on)")
    ax.set_ylabel(
        "mean OSPA [m]" if many else f"position RMSE after {rows[0]['burn_in_scans']} scans [m]"
    )
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    _unstack(fig, ax, labels)
    path = out / "pareto.png"
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def _unstack(fig: Any, ax: Any, labels: Sequence[Any]) -> None:
    """Move the points' names down, from the highest point's, until none overlaps another
    name or the title: with ``--budget match`` every budgeted policy stands on one vertical
    line, often metres apart, and names printed at a fixed offset ran over each other (points
    that coincide get their names one under the other)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    placed = [ax.title.get_window_extent(renderer)]
    per_px = 72.0 / fig.dpi  # offset points per pixel
    for ann in sorted(labels, key=lambda a: -float(ax.transData.transform(a.xy)[1])):
        box = ann.get_window_extent(renderer)
        moved = 0.0
        clash = True
        while clash:
            clash = False
            for other in placed:
                if box.overlaps(other):
                    step = box.y1 - other.y0 + 1.0
                    box = box.translated(0.0, -step)
                    moved += step
                    clash = True
        if moved:
            dx, dy = ann.xyann
            ann.xyann = (dx, dy - moved * per_px)
        placed.append(box)


def curves_figure(out: Path, data: Mapping[str, np.ndarray], select: Sequence[int]) -> Path:
    """``curves.png``: per scan the RMSE (or OSPA with targets) and the sensors on, per policy
    ``select``, with their 95 % bands over seeds."""
    import matplotlib  # the figure only: start-up of the runs (and of the workers)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    many = "ospa" in data
    acc = "ospa" if many else "rmse"
    fig, axes = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    keys = [str(k) for k in data["points"]]
    colors = _colors(len(keys))
    for i in select:
        scans = np.arange(1, data[acc].shape[1] + 1)
        label = keys[i].replace("policy=", "").replace(",budget=", " K=")
        for ax, name in zip(axes, (acc, "sensors"), strict=True):
            ax.plot(scans, data[name][i], color=colors[i], lw=1.2, label=label)
            lo, hi = data[f"{name}_lo"][i], data[f"{name}_hi"][i]
            if np.all(np.isfinite(lo)):
                ax.fill_between(scans, lo, hi, color=colors[i], alpha=0.2, lw=0)
    axes[0].set_ylabel("OSPA [m]" if many else "position RMSE [m]")
    axes[1].set_ylabel("sensors on")
    axes[1].set_xlabel("scan")
    n = int(np.min(data["seeds"])) if len(data["seeds"]) else 0
    axes[0].set_title(f"per scan, mean over {n} seeds with 95 % bands")
    axes[0].legend(fontsize=8, ncol=2)
    for ax in axes:  # RMSE, OSPA and sensors on are >= 0 (a t band may reach below: not drawn)
        ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path = out / "curves.png"
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


__all__ = [
    "MATCH",
    "Plan",
    "budget_for",
    "compare_outcome",
    "curves",
    "curves_figure",
    "format_table",
    "make_figure",
    "parse_budget",
    "parse_policies",
    "run_trial",
    "scenario_for",
    "summarise",
    "takes_budget",
    "trial_key",
    "write_table",
]


def figure_title(meta: Mapping[str, Any]) -> str:
    """``pareto.png``'s title from the table's meta data (the command's, and ``covnet plot``'s
    when it redraws the figure from ``compare.json``)."""
    return (
        f"{meta.get('scenario', '')}: allocation policies, metric {meta.get('metric', '?')}, "
        f"{meta.get('runs', '?')} paired seeds"
    )
