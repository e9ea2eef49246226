"""The scenario's checks beyond each record's (:func:`semantic_problems`, run by
:func:`covnet.config.validate` after the structure): the schedules, each sensor's keys against
its model's, the targets and their manoeuvres, the allocation constraints, what the search and
the many-target allocator cannot do, the peer graph; each problem with its path.  And the one
warning (:func:`reach_warnings`): a sensor that never covers any target."""

from __future__ import annotations

from typing import Any

import numpy as np

from covnet.core.metrics import METRICS
from covnet.core.sensor_models import SENSOR_MODELS
from covnet.covariance_control.config.fusion import PeerSpec
from covnet.covariance_control.config.scenario import Scenario
from covnet.covariance_control.config.sensors import (
    _SENSOR_EXTRAS,
    SensorSpec,
    fields_record,
    in_coverage,
)
from covnet.covariance_control.config.surveillance_checks import surveillance_problems
from covnet.covariance_control.config.targets import DesiredSpec, segments
from covnet.covariance_control.fusion_rules import FUSION_RULES, refusal, rule_for
from covnet.covariance_control.searches import (
    AUTO_EXACT_MAX,
    BOUNDED_OPTIONS,
    MANY_EXACT_MAX,
    SEARCHES,
)


def _schedule_problems(path: str, schedule: tuple[DesiredSpec, ...]) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    if schedule[0].from_scan != 1:
        problems.append((f"{path}[0].from_scan", "the first entry must start at scan 1"))
    for i, d in enumerate(schedule):
        if (d.diag is None) == (d.matrix is None):
            problems.append((f"{path}[{i}]", "give exactly one of 'diag' or 'matrix'"))
            continue
        if d.matrix is not None and len(d.matrix) != 4:
            problems.append((f"{path}[{i}].matrix", "must be 4x4"))
            continue
        M = d.as_matrix()
        if not np.allclose(M, M.T) or np.linalg.eigvalsh(0.5 * (M + M.T)).min() <= 0:
            problems.append((f"{path}[{i}]", "must be symmetric positive definite"))
        if i > 0 and d.from_scan <= schedule[i - 1].from_scan:
            problems.append((f"{path}[{i}].from_scan", "must increase along the schedule"))
    return problems


def _sensor_problems(sc: Scenario) -> list[tuple[str, str]]:
    """Each sensor's keys against its model's (missing, or another model's, or nobody's),
    its placement and coverage; without ``targets:`` only the paper's position sensor."""
    problems: list[tuple[str, str]] = []
    for i, s in enumerate(sc.sensors):
        where = f"sensors[{i}]"
        entry = SENSOR_MODELS[s.model]
        own = fields_record(entry.config_fields).model_fields
        need = [k for k, f in own.items() if f.is_required()]
        for key in s.missing_fields:
            problems.append(
                (
                    f"{where}.{key}",
                    f"missing required key (a {s.model} sensor needs {', '.join(need)})",
                )
            )
        for key in s.foreign_fields:
            others = [
                n
                for n, m in SENSOR_MODELS.items()
                if key in fields_record(m.config_fields).model_fields
            ]
            if others:
                why = f"not a field of model {s.model} (only for {', '.join(others)} sensors)"
            else:
                common = [k for k in SensorSpec.model_fields if k != "params"]
                why = (
                    f"unknown key: not a field of model {s.model} (its keys: {', '.join(own)}; "
                    f"every sensor's: {', '.join(common)})"
                )
            problems.append((f"{where}.{key}", why))
        # (coverage without targets: is refused below, a position for it would be too)
        covers = sc.multitarget and (s.max_range_m or s.fov)
        if s.position_m is None and (entry.measures_from_position or covers):
            what = "measures from" if entry.measures_from_position else "has coverage around"
            problems.append(
                (f"{where}.position_m", f"missing required key (a {s.model} sensor {what} it)")
            )
        if not sc.multitarget:
            for key, default in _SENSOR_EXTRAS.items():
                if getattr(s, key) != default:
                    problems.append(
                        (
                            f"{where}.{key}",
                            "needs a 'targets:' list (a config with the one 'target:' is the "
                            "paper's linear scenario: position sensors that always detect, "
                            "no clutter)",
                        )
                    )
    return problems


def _target_problems(sc: Scenario) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    assert sc.targets is not None
    if not sc.targets and sc.surveillance is None:
        return [("targets", "list at least one target")]
    for key in ("target", "desired"):
        if key in sc.model_fields_set:
            problems.append(
                (key, "not with 'targets:' (each target has its own state and 'desired')")
            )
    for i, t in enumerate(sc.targets):
        where = f"targets[{i}]"
        if t.desired:  # missing: surveillance_problems says whether it is needed
            problems += _schedule_problems(f"{where}.desired", t.desired)
        spans: list[tuple[int, int, int]] = []
        for m, man in enumerate(t.manoeuvres):
            mw = f"{where}.manoeuvres[{m}]"
            if man.to_scan <= man.from_scan:
                problems.append((f"{mw}.to_scan", "must be after from_scan"))
            if man.to_scan > sc.scans:
                problems.append((f"{mw}.to_scan", f"beyond the run's {sc.scans} scans"))
            need, other = (
                ("turn_rate_deg_s", "accel_mps2")
                if man.kind == "turn"
                else ("accel_mps2", "turn_rate_deg_s")
            )
            if getattr(man, need) is None:
                problems.append((f"{mw}.{need}", f"missing required key (a {man.kind} needs it)"))
            if getattr(man, other) is not None:
                problems.append((f"{mw}.{other}", f"not for a {man.kind}"))
            for a, b, other_m in spans:
                if man.from_scan < b and a < man.to_scan:
                    problems.append((mw, f"overlaps manoeuvres[{other_m}]"))
            spans.append((man.from_scan, man.to_scan, m))
    return problems


def semantic_problems(sc: Scenario) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    ids = sc.sensor_ids
    seen = set(ids)
    if sc.multitarget:
        problems += _target_problems(sc)
    elif not sc.desired:
        problems.append(("desired", "missing required key (the desired-covariance schedule)"))
    else:
        problems += _schedule_problems("desired", sc.desired)
    problems += _sensor_problems(sc)
    if not sc.multitarget:
        for key in ("association", "ospa"):
            if key in sc.model_fields_set:
                problems.append((key, "only used with 'targets:' (many targets)"))
        for key in ("detection", "max_per_target"):
            if key in sc.allocation.model_fields_set:
                problems.append((f"allocation.{key}", "only used with 'targets:' (many targets)"))
    al = sc.allocation
    if not al.metrics:
        problems.append(("allocation.metrics", "name at least one metric"))
    for field in ("required", "excluded"):
        for i, sid in enumerate(getattr(al, field)):
            if sid not in seen:
                problems.append((f"allocation.{field}[{i}]", f"no sensor with id {sid!r}"))
    both = set(al.required) & set(al.excluded)
    if both:
        problems.append(("allocation", f"sensors both required and excluded: {sorted(both)}"))
    problems += _search_problems(sc)
    problems += _policy_problems(sc)
    problems += _sweep_axis_problems(sc)
    problems += surveillance_problems(sc)
    problems += _peer_problems(sc.fusion.peer, ids)
    if set(al.excluded) >= set(ids):
        problems.append(("allocation.excluded", "excludes every sensor"))
    if al.max_active is not None:
        if al.max_active < len(set(al.required)):
            problems.append(
                ("allocation.max_active", f"smaller than the {len(al.required)} required sensors")
            )
        if al.max_active > len(ids):
            problems.append(("allocation.max_active", f"more than the {len(ids)} sensors"))
    n_req = len(set(al.required))
    if sc.multitarget and al.max_per_target is not None and sc.targets is not None:
        room = al.max_per_target * len(sc.targets)
        if sc.surveillance is None and n_req > room:
            # every scan turned every sensor off (exit 0), or, one target, a traceback
            problems.append(
                (
                    "allocation.max_per_target",
                    f"{al.max_per_target} x {len(sc.targets)} targets: room for {room} sensors, "
                    f"fewer than the {n_req} of allocation.required (on every scan)",
                )
            )
    if sc.multitarget:
        problems += _multitarget_fusion_problems(sc)
    return problems


#: the exact many-target search's limit on the sensors that can be on (``search: exact``
#: refuses more; ``auto`` is ``bounded`` beyond)
MULTITARGET_MAX_SENSORS = MANY_EXACT_MAX


def _multitarget_fusion_problems(sc: Scenario) -> list[tuple[str, str]]:
    """What the many-target scenario does not (yet) do, said where it is asked for."""
    problems: list[tuple[str, str]] = []
    excluded = set(sc.allocation.excluded)
    candidates = [s for s in sc.sensor_ids if s not in excluded]
    search = SEARCHES.get(sc.allocation.search)
    used = None if search is None else search.resolved_many(len(candidates))
    if used is not None and used.many is None:
        problems.append(
            ("allocation.search", f"{used.name} ({used.words}) has no many-target form")
        )
    elif used is not None and used.many is not None:
        top = used.many.max_sensors
        if top is not None and len(candidates) > top:
            problems.append(
                (
                    "sensors",
                    f"with 'targets:' search {used.name} is {used.words}; over assignments it "
                    f"enumerates tables of 2^N entries, at most {top} sensors that can be on, "
                    f"and {len(candidates)} are not in allocation.excluded: use search bounded, "
                    "greedy or auto, or exclude some",
                )
            )
    mode = sc.fusion.mode
    if _surveillance_refuses_mode(sc):
        pass  # its own check names the cause (central only), once
    elif sc.fusion.has_centre and (why := refusal(rule_for(sc.fusion), "targets")) is not None:
        problems.append(("fusion.mode", f"{mode} {why}"))
    elif not sc.fusion.has_centre:
        problems.append(
            (
                "fusion.mode",
                "peer is not available with 'targets:': the peer nodes' mirror of every node's "
                "filter is single-target "
                + ("(use central)" if sc.surveillance is not None else "(use central or info)"),
            )
        )
    if sc.allocation.account_for_loss:
        problems.append(
            (
                "allocation.account_for_loss",
                "not available with 'targets:' (the many-target allocator scores pd · J only)",
            )
        )
    lat = sc.network.latency
    if "missed_command" in lat.model_fields_set and lat.missed_command != "off":
        problems.append(
            (
                "network.latency.missed_command",
                f"{lat.missed_command} is not available with 'targets:': a sensor whose command "
                "never came does not know which target to dwell on, nor the clutter window; "
                "it dwells on nothing (off, the only choice with targets)",
            )
        )
    return problems


def _surveillance_refuses_mode(sc: Scenario) -> bool:
    """A surveillance config whose fusion centre is not ``central``: its own check
    (:mod:`.surveillance_checks`) refuses ``fusion.mode``; the other checks that follow from
    the mode said it again, two of them contradicting it ("use central or info")."""
    return sc.surveillance is not None and sc.fusion.has_centre and sc.fusion.mode != "central"


def _search_problems(sc: Scenario) -> list[tuple[str, str]]:
    """What the search entry (:data:`SEARCHES`) cannot do with this config, in its own words."""
    al = sc.allocation
    problems: list[tuple[str, str]] = []
    search = SEARCHES.get(al.search)
    if search is None:  # reported by the field's check
        return problems
    for opt in BOUNDED_OPTIONS:
        if getattr(al, opt) is not None and opt not in search.options:
            users = " or ".join(k for k, s in _by_options() if opt in s.options)
            why = f"only used with search: {users}, not {al.search}"
            problems.append((f"allocation.{opt}", why))
    if (
        search.information_form
        and (not sc.fusion.has_centre or not rule_for(sc.fusion).information_form)
        and not _surveillance_refuses_mode(sc)  # (the mode is the cause, named once)
    ):
        problems.append(
            (
                "allocation.search",
                f"{al.search} needs a fusion centre in the information form (fusion.mode "
                f"central or info); {sc.fusion.mode} decides over every subset",
            )
        )
    n = len(set(sc.sensor_ids) - set(al.excluded))
    used = search.resolved(n)
    as_ = "" if used is search else f" (with {n} candidate sensors: {used.name})"
    # a metric without an interval bound: no branch and bound, and the exact search then
    # enumerates every subset (2^n: at n = 64 it asked for 32 PiB and died with a traceback)
    unbounded = [m for m in al.metrics if m in METRICS and METRICS[m].interval_bound is None]
    for m in unbounded:
        if "interval_bound" in used.needs:
            why = (
                f"{al.search}{as_} is {used.words}: it needs each metric's interval bound, and "
                f"metric {m!r} has none (its METRICS entry's interval_bound is None); choose "
                "search: exact or greedy for it"
            )
        elif used.name == "exact" and n > AUTO_EXACT_MAX and not sc.multitarget:
            why = (
                f"exact with {n} candidate sensors: metric {m!r} has no interval bound (its "
                f"METRICS entry's interval_bound is None), so every subset (2^{n}) would be "
                f"evaluated; at most {AUTO_EXACT_MAX} candidate sensors for it: choose search: "
                "greedy, or exclude sensors"
            )
        else:
            continue
        problems.append(("allocation.search", why))
    return problems


def _policy_problems(sc: Scenario) -> list[tuple[str, str]]:
    """What the allocation policy's entry (:data:`covnet.core.allocation.policy_registry.
    POLICIES`) cannot do with this config, in its own words."""
    al = sc.allocation
    if al.policy == "covariance_control":
        if al.budget is not None:
            return [
                (
                    "allocation.budget",
                    "only used by the baseline policies (allocation.policy); covariance "
                    "control's budget is allocation.max_active",
                )
            ]
        return []
    # start-up: the baseline policies' registry only for a config that names one
    from covnet.core.allocation.policy_registry import POLICIES

    pol = POLICIES.get(al.policy)
    if pol is None:  # reported by the field's check
        return []
    problems: list[tuple[str, str]] = []
    if al.budget is not None and not (pol.needs_budget or pol.reward is not None):
        # it ran every sensor while summary.json said "budget": K
        problems.append(
            (
                "allocation.budget",
                f"policy {al.policy} ({pol.summary}) takes no budget",
            )
        )
    if pol.needs_budget and al.budget is None and al.max_active is None:
        problems.append(
            (
                "allocation.budget",
                f"policy {al.policy} ({pol.summary}) needs a budget K: set allocation.budget "
                "(or allocation.max_active)",
            )
        )
    if al.budget is not None and al.budget > len(sc.sensor_ids):  # as max_active
        problems.append(("allocation.budget", f"more than the {len(sc.sensor_ids)} sensors"))
    if al.budget is not None and al.max_active is not None and al.budget > al.max_active:
        # the policy ran max_active sensors while the results said budget
        problems.append(
            (
                "allocation.budget",
                f"{al.budget}: more than allocation.max_active {al.max_active} (a policy turns "
                "on at most max_active sensors)",
            )
        )
    if al.budget is not None and al.budget < len(set(al.required)):  # every run: a traceback
        problems.append(
            (
                "allocation.budget",
                f"{al.budget}: smaller than the {len(set(al.required))} required sensors "
                "(allocation.required: on every scan)",
            )
        )
    if sc.multitarget and not pol.many_targets:
        problems.append(("allocation.policy", f"{al.policy} has no many-target form"))
    if al.account_for_loss and pol.reward is None:
        # accepted, and its runs were those of false: nothing read the scaled information
        problems.append(
            (
                "allocation.account_for_loss",
                f"policy {al.policy} ({pol.summary}) reads no sensor information, the "
                "information account_for_loss scales by each sensor's delivery probability",
            )
        )
    if not sc.fusion.has_centre or not rule_for(sc.fusion).information_form:
        # all_on, random and round_robin read no J_j: the reason given for them was not theirs
        why = (
            f"{al.policy} decides from the sensors' information J_j (a fusion centre in the "
            "information form: fusion.mode central or info)"
            if pol.reward is not None
            else f"a baseline such as {al.policy} is run only by a fusion centre in the "
            "information form (fusion.mode central or info); ci and peer decide by their own "
            "search over every subset"
        )
        problems.append(("allocation.policy", f"{why}; {sc.fusion.mode} is not"))
    if al.search != "auto":
        problems.append(
            ("allocation.search", f"only used by policy covariance_control, not {al.policy}")
        )
    for opt in BOUNDED_OPTIONS:
        if getattr(al, opt) is not None:
            problems.append(
                (f"allocation.{opt}", f"only used by policy covariance_control, not {al.policy}")
            )
    if al.policy == "all_on" and al.max_active is not None:
        n = len(set(sc.sensor_ids) - set(al.excluded))
        if al.max_active < n:
            problems.append(
                (
                    "allocation.max_active",
                    f"policy all_on turns every available sensor on ({n}), more than "
                    f"max_active {al.max_active}",
                )
            )
    if al.policy == "all_on" and al.max_per_target is not None and sc.multitarget:
        n = len(set(sc.sensor_ids) - set(al.excluded))
        if al.max_per_target < n:
            # every run stopped with a traceback at the first scan where more sensors than the
            # cap covered the same targets; the coverage changes every scan, so no count of
            # sensors and targets can tell the runs that would end
            problems.append(
                (
                    "allocation.max_per_target",
                    f"{al.max_per_target} with policy all_on: all_on turns every available "
                    f"sensor ({n}) on, each on a target it covers, and a cap below {n} leaves a "
                    "sensor with no target whenever more sensors than the cap cover the same "
                    "targets (the run stops there): drop max_per_target or use a policy with a "
                    "budget",
                )
            )
    return problems


def _sweep_axis_problems(sc: Scenario) -> list[tuple[str, str]]:
    """A ``sweep.modes`` (or ``sweep.account_for_loss``) entry of a ``sweep:`` section that the
    allocation's search or policy refuses (as they refuse ``fusion.mode``,
    ``allocation.account_for_loss``): ``covnet sweep`` refuses its grid points; ``covnet
    check`` said nothing.  Only an axis given a value other than its default: a normalised
    config spells the defaults out and must validate as its config did, and a ``sweep:``
    section of seeds alone must not stop ``covnet run`` of a config whose search or policy
    refuses ``ci`` (the default grid's points are refused by ``covnet sweep`` itself, before
    any run: :func:`covnet.covariance_control.sweep.refused_point`)."""
    sw = sc.sweep
    if sw is None or sc.multitarget:
        return []  # the sweep of many targets and of surveillance: refused or checked apart
    if not sc.fusion.has_centre:
        return []  # covnet sweep refuses a peer config as a whole
    own = set(_search_problems(sc) + _policy_problems(sc))
    problems: list[tuple[str, str]] = []
    axes = (("modes", "fusion", "mode"), ("account_for_loss", "allocation", "account_for_loss"))
    defaults = type(sw).model_fields
    for axis, part, key in axes:
        if getattr(sw, axis) == defaults[axis].get_default(call_default_factory=True):
            continue  # the default grid: covnet sweep refuses its points itself
        for i, value in enumerate(getattr(sw, axis)):
            if value == getattr(getattr(sc, part), key):
                continue  # checked as the config's own key
            if axis == "modes" and value not in FUSION_RULES:
                continue  # refused as a name
            section = getattr(sc, part).model_copy(update={key: value})
            at = sc.model_copy(update={part: section})
            text = str(value).lower() if isinstance(value, bool) else value
            for path, why in _search_problems(at) + _policy_problems(at):
                if (path, why) not in own:
                    problems.append((f"sweep.{axis}[{i}]", f"{text}: {path}: {why}"))
    return problems


def _by_options() -> list[tuple[str, Any]]:
    """The search entries, bounded first (the wording of the options' refusals)."""
    return sorted(SEARCHES.items(), key=lambda kv: (kv[0] != "bounded", kv[0] == "auto"))


def _peer_problems(peer: PeerSpec, ids: tuple[str, ...]) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    known = set(ids)
    if peer.hub is not None and peer.hub not in known:
        problems.append(("fusion.peer.hub", f"no sensor with id {peer.hub!r}"))
    if peer.graph == "custom" and not peer.edges:
        problems.append(("fusion.peer.edges", "a custom graph needs at least one edge"))
    if peer.graph != "custom" and peer.edges:
        problems.append(("fusion.peer.edges", "edges are only used with graph: custom"))
    for i, (a, b) in enumerate(peer.edges):
        for end, sid in enumerate((a, b)):
            if sid not in known:
                problems.append((f"fusion.peer.edges[{i}][{end}]", f"no sensor with id {sid!r}"))
        if a == b:
            problems.append((f"fusion.peer.edges[{i}]", f"a self-loop on {a!r}"))
    seen: dict[frozenset[str], int] = {}
    for i, (a, b) in enumerate(peer.edges):  # a link is undirected: [a, b] is [b, a]
        first = seen.setdefault(frozenset((a, b)), i)
        if first != i and a != b:
            problems.append((f"fusion.peer.edges[{i}]", f"the link of edges[{first}] again"))
    if peer.hub is not None and peer.graph != "star":
        problems.append(("fusion.peer.hub", "only used with graph: star"))
    return problems


def nominal_positions(sc: Scenario) -> np.ndarray:
    """``(T, scans, 2)``: each target's position at scans ``1..scans`` without process noise
    (its constant velocity and manoeuvres), what :func:`reach_warnings` looks at."""
    from covnet.core.manoeuvre import manoeuvring_trajectory  # start-up: configs with targets

    assert sc.targets is not None
    out = np.empty((len(sc.targets), sc.scans, 2))
    for i, t in enumerate(sc.targets):
        x0 = [t.initial_position_m[0], t.initial_velocity_mps[0]]
        x0 += [t.initial_position_m[1], t.initial_velocity_mps[1]]
        traj = manoeuvring_trajectory(
            x0, sc.period_s, 0.0, sc.scans, np.random.default_rng(0), segments(t)
        )
        out[i] = traj[:, [0, 2]]
    return out


def reach_warnings(sc: Scenario) -> list[tuple[str, str]]:
    """The sensors that never cover any target at any scan (on the noise-free trajectories of
    :func:`nominal_positions`) nor, in surveillance with a search grid, any search cell (its
    centre, as :func:`covnet.core.surveillance.search_cells.coverage_of` decides): allowed,
    never allocated, probably a mistake.  Nothing to cover (surveillance with no target and no
    grid): no warning."""
    if not sc.multitarget or not any(s.max_range_m or s.fov for s in sc.sensors):
        return []
    xy = nominal_positions(sc).reshape(-1, 2)
    grid = sc.surveillance.grid() if sc.surveillance is not None else None
    if grid is not None:
        xy = np.concatenate([xy, grid.centres()])
    if not xy.size:
        return []
    what = "any target or search cell" if grid is not None else "any target"
    out = []
    for i, s in enumerate(sc.sensors):
        if in_coverage(s, xy).any():
            continue
        assert s.position_m is not None
        d = np.hypot(xy[..., 0] - s.position_m[0], xy[..., 1] - s.position_m[1]).min()
        reach = f"max_range_m {s.max_range_m:g}" if s.max_range_m else "no range limit"
        fov = (
            f", fov {s.fov.center_deg:g} ± {s.fov.half_width_deg:g} deg"
            if s.fov is not None
            else ""
        )
        out.append(
            (
                f"sensors[{i}]",
                f"{s.id} never covers {what} ({reach}{fov}; nearest approach "
                f"{d / 1e3:.1f} km): it can never be allocated",
            )
        )
    return out
