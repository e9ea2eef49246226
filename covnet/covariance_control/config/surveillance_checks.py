"""The checks of a config's ``surveillance:`` block and of the keys only it uses
(:func:`surveillance_problems`, one of the scenario's semantic checks): each problem with its
path, impossible combinations named (search cells no sensor can search, a birth region outside
the area, what the surveillance world does not support yet)."""

from __future__ import annotations

import numpy as np

from covnet.covariance_control.config.scenario import Scenario
from covnet.covariance_control.config.sensors import in_coverage
from covnet.covariance_control.config.surveillance import CovSpec, SurveillanceSpec
from covnet.covariance_control.fusion_rules import rule_for
from covnet.covariance_control.searches import AUTO_MODES_MAX

__all__ = ["surveillance_problems", "search_sensors"]

#: the truth-only keys of a target with ``surveillance:`` (the manager knows no target)
_TRUTH_ONLY = (
    "cued",
    "P0_diag",
    "id",
    "initial_position_m",
    "initial_velocity_mps",
    "accel_noise_std_mps2",
    "manoeuvres",
    "appears_at_scan",
    "leaves_at_scan",
)


def _cov_problems(path: str, c: CovSpec) -> list[tuple[str, str]]:
    if (c.diag is None) == (c.matrix is None):
        return [(path, "give exactly one of 'diag' or 'matrix'")]
    M = np.diag(c.diag) if c.diag is not None else np.asarray(c.matrix, dtype=np.float64)
    if not np.allclose(M, M.T) or np.linalg.eigvalsh(0.5 * (M + M.T)).min() <= 0:
        return [(path, "must be symmetric positive definite")]
    return []


def _box_problems(path: str, lo: tuple[float, ...], hi: tuple[float, ...]) -> list[tuple[str, str]]:
    if not (lo[0] < hi[0] and lo[1] < hi[1]):
        return [(path, f"min_m {list(lo)} must be below max_m {list(hi)} in x and y")]
    return []


def search_sensors(sc: Scenario) -> list[int]:
    """The sensors that can search: those whose returns can start a track (their model is in
    :data:`~covnet.core.surveillance.tracks.INITIATORS`: a bearing alone cannot, spec §2)."""
    # start-up: the surveillance core (and scipy with it) only for surveillance configs
    from covnet.core.surveillance.tracks import INITIATORS

    return [i for i, s in enumerate(sc.sensors) if s.model in INITIATORS]


def _target_keys(sc: Scenario, spec: SurveillanceSpec | None) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    for i, t in enumerate(sc.targets or ()):
        where = f"targets[{i}]"
        if spec is None:
            for key in ("appears_at_scan", "leaves_at_scan", "cued"):
                if key in t.model_fields_set:
                    problems.append((f"{where}.{key}", "only used with 'surveillance:'"))
            if not t.desired:
                problems.append((f"{where}.desired", "missing required key (its schedule)"))
            continue
        # a key the manager would use, given a value (a normalised config spells out defaults)
        defaults = type(t).model_fields
        given = [
            k
            for k in sorted(t.model_fields_set - set(_TRUTH_ONLY))
            if getattr(t, k) != defaults[k].get_default(call_default_factory=True)
        ]
        for key in given:
            problems.append(
                (
                    f"{where}.{key}",
                    "not with 'surveillance:' (the targets are the truth only: "
                    "the manager's tracks get surveillance.desired)",
                )
            )
        if t.cued and t.appears_at_scan != 1:
            problems.append((f"{where}.cued", "only a target present at scan 1 can be cued"))
        if t.appears_at_scan > sc.scans:
            problems.append((f"{where}.appears_at_scan", f"beyond the run's {sc.scans} scans"))
        if t.leaves_at_scan is not None and t.leaves_at_scan <= t.appears_at_scan:
            problems.append((f"{where}.leaves_at_scan", "must be after appears_at_scan"))
        for m, man in enumerate(t.manoeuvres):
            if man.from_scan < t.appears_at_scan - 1:
                problems.append((f"{where}.manoeuvres[{m}].from_scan", "before the target appears"))
    return problems


#: the keys of the latency grid (``covnet sweep`` of a config without surveillance), which the
#: surveillance sweep (the search weight λ) never reads
_LATENCY_GRID = ("delay_ms", "delay_kind", "loss", "modes", "account_for_loss", "late", "metric")


def _latency_grid_keys(sc: Scenario) -> list[tuple[str, str]]:
    """A surveillance config's ``sweep:`` key of the latency grid, given a value (a normalised
    config spells out the defaults): its sweep ran the λ grid alone and said nothing."""
    sw = sc.sweep
    assert sw is not None
    defaults = type(sw).model_fields
    return [
        (
            f"sweep.{key}",
            "not with 'surveillance:' (its sweep is the search weight λ alone: "
            "sweep.search_weight and sweep.seeds, over allocation.metrics or --metric)",
        )
        for key in _LATENCY_GRID
        if key in sw.model_fields_set
        and getattr(sw, key) != defaults[key].get_default(call_default_factory=True)
    ]


def surveillance_problems(sc: Scenario) -> list[tuple[str, str]]:
    """Every problem of the surveillance keys (module docstring)."""
    spec = sc.surveillance
    problems = _target_keys(sc, spec)
    grid = None if sc.sweep is None else sc.sweep.search_weight
    if grid is not None:
        if spec is None:
            problems.append(("sweep.search_weight", "only with 'surveillance:' (λ of the search)"))
        elif not grid or any(w < 0 for w in grid):
            problems.append(("sweep.search_weight", f"give weights >= 0, got {list(grid)}"))
        elif spec.search is None:
            problems.append(("sweep.search_weight", "needs surveillance.search (its cells)"))
    if spec is not None and sc.sweep is not None:
        problems += _latency_grid_keys(sc)
    if spec is None:
        if sc.association.method == "jpda":
            problems.append(
                (
                    "association.method",
                    "jpda needs 'surveillance:' (without it each dwell sees "
                    "one target, and JPDA is the PDA: use pda)",
                )
            )
        return problems
    if sc.targets is None:
        problems.append(
            (
                "targets",
                "missing required key (with 'surveillance:' the truth; give [] for births only)",
            )
        )
    problems += _box_problems("surveillance.area", spec.area.min_m, spec.area.max_m)
    lo, hi = np.asarray(spec.area.min_m), np.asarray(spec.area.max_m)
    if spec.births is not None:
        for r, reg in enumerate(spec.births.regions):
            where = f"surveillance.births.regions[{r}]"
            bad = _box_problems(where, reg.min_m, reg.max_m)
            problems += bad
            if not bad and not (
                np.all(np.asarray(reg.min_m) >= lo) and np.all(np.asarray(reg.max_m) <= hi)
            ):
                problems.append((where, "outside the area (a birth region must lie inside it)"))
            for key in ("speed_mps", "heading_deg"):
                a, b = getattr(reg, key)
                if a > b:
                    problems.append(
                        (f"{where}.{key}", f"[low, high] with low <= high, got {[a, b]}")
                    )
            if reg.speed_mps[0] < 0:
                problems.append((f"{where}.speed_mps", "speeds must be >= 0"))
    c = spec.tracks.confirm
    if c.m > c.n:
        problems.append(("surveillance.tracks.confirm.m", f"must be <= n ({c.n})"))
    problems += _cov_problems("surveillance.desired.confirmed", spec.desired.confirmed)
    problems += _cov_problems("surveillance.desired.tentative", spec.desired.tentative)
    if spec.search is not None:
        problems += _search_problems(sc, spec)
    if not search_sensors(sc):
        problems.append(
            (
                "sensors",
                "with 'surveillance:' at least one sensor must measure range "
                "(position or range_bearing): bearings alone cannot start a track",
            )
        )
    if sc.association.method == "nearest":  # it was accepted, and JPDA ran in its name
        problems.append(
            (
                "association.method",
                "nearest: not with 'surveillance:' (the manager shares each dwell's returns "
                "among the tracks by JPDA): jpda, or leave the key out",
            )
        )
    # peer mode (no centre) is refused by the many-target checks, naming peer
    if sc.fusion.has_centre and (rule := rule_for(sc.fusion)).name != "central":
        problems.append(
            (
                "fusion.mode",
                f"{rule.name}: not with 'surveillance:' (the manager's "
                "tracks are not the sensors': only central fusion of returns)",
            )
        )
    if not sc.network.latency.is_ideal(sc.sensor_ids):
        problems.append(
            (
                "network.latency",
                "not with 'surveillance:' yet (late returns would "
                "re-run track initiation and deletion)",
            )
        )
    if sc.allocation.required:
        problems.append(
            (
                "allocation.required",
                "not with 'surveillance:' yet (a required sensor would have to dwell on a "
                "track or a cell every scan)",
            )
        )
    return problems


def _search_problems(sc: Scenario, spec: SurveillanceSpec) -> list[tuple[str, str]]:
    assert spec.search is not None
    problems: list[tuple[str, str]] = []
    if _box_problems("", spec.area.min_m, spec.area.max_m):
        return problems  # said at surveillance.area
    grid = spec.grid()
    assert grid is not None
    able = search_sensors(sc)
    for c, centre in enumerate(grid.centres()):
        if not any(in_coverage(sc.sensors[j], centre) for j in able):
            problems.append(
                (
                    "surveillance.search.cells",
                    f"cell {c} (centre {centre.round(1).tolist()} m) "
                    "is outside every range-measuring sensor's coverage: no sensor can search it",
                )
            )
    n_on = len(sc.sensors) - len(sc.allocation.excluded)
    C = spec.search.cells.nx * spec.search.cells.ny
    if sc.allocation.search == "exact" and (C + 2) ** n_on > AUTO_MODES_MAX:
        problems.append(
            (
                "allocation.search",
                f"exact would weigh up to ({C} cells + a track + off)^{n_on} assignments a scan "
                "(and cells of equal mass tie exactly): use auto, bounded or greedy",
            )
        )
    if spec.search.birth_intensity is None and spec.births is None and spec.search.u0 == 0.0:
        problems.append(
            (
                "surveillance.search",
                "u0 is 0 and no birth intensity reaches the "
                "cells: the search would never be worth a dwell (give u0, "
                "birth_intensity or births)",
            )
        )
    return problems
