"""Surveillance through the one engine (``surveillance:`` configs): the config's refusals, the
truth, the spec's reductions (surveillance.md §6), the allocator over tracks and cells, and
``covnet run`` end to end."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from covnet.config import ConfigError
from covnet.core.allocation.assignment import (
    CellTerms,
    allocate_assignments,
    allocate_assignments_exhaustive,
)
from covnet.covariance_control import drive, surveillance, targets
from covnet.covariance_control.config import from_dict, load, normalised
from covnet.covariance_control.surveillance_centre import SurveillanceCentre

SENSORS = [
    {
        "id": "P1",
        "position_m": [5000.0, 5000.0],
        "sigma_x_m": 20.0,
        "sigma_y_m": 10.0,
        "rho": 0.3,
        "max_range_m": 30000.0,
        "pd": 1.0,
        "clutter_rate": 0.0,
    },
    {
        "id": "P2",
        "position_m": [15000.0, 15000.0],
        "sigma_x_m": 10.0,
        "sigma_y_m": 20.0,
        "rho": -0.3,
        "max_range_m": 30000.0,
        "pd": 1.0,
        "clutter_rate": 0.0,
    },
    {
        "id": "R1",
        "model": "range_bearing",
        "position_m": [0.0, 0.0],
        "sigma_range_m": 20.0,
        "sigma_bearing_mrad": 2.0,
        "max_range_m": 40000.0,
        "pd": 1.0,
        "clutter_rate": 0.0,
    },
    {
        "id": "B1",
        "model": "bearing",
        "position_m": [10000.0, 0.0],
        "sigma_bearing_mrad": 1.0,
        "max_range_m": 40000.0,
        "pd": 1.0,
        "clutter_rate": 0.0,
    },
]


def base(**over) -> dict:
    d = {
        "name": "surv-test",
        "seed": 7,
        "scans": 16,
        "targets": [
            {
                "id": "A",
                "initial_position_m": [3000.0, 3000.0],
                "initial_velocity_mps": [100.0, 0.0],
            },
            {
                "id": "B",
                "initial_position_m": [15000.0, 6000.0],
                "initial_velocity_mps": [0.0, 80.0],
                "appears_at_scan": 4,
            },
            {
                "id": "C",
                "initial_position_m": [6000.0, 16000.0],
                "initial_velocity_mps": [-50.0, -50.0],
                "appears_at_scan": 2,
                "leaves_at_scan": 12,
            },
        ],
        "sensors": copy.deepcopy(SENSORS),
        "association": {"method": "jpda"},
        "surveillance": {
            "area": {"min_m": [0.0, 0.0], "max_m": [20000.0, 20000.0]},
            "tracks": {
                "confirm": {"m": 2, "n": 3},
                "delete_after_misses": 3,
                "initiation": {"velocity_std_mps": 150.0},
            },
            "search": {
                "cells": {"nx": 2, "ny": 2},
                "u0": 0.5,
                "birth_intensity": 0.02,
                "weight": 30.0,
            },
            "desired": {
                "confirmed": {"diag": [400.0, 100.0, 400.0, 100.0]},
                "tentative": {"diag": [900.0, 400.0, 900.0, 400.0]},
            },
        },
        "allocation": {"metrics": ["spectral"], "search": "greedy"},
    }
    d.update(over)
    return d


def problems(d: dict) -> list[tuple[str, str]]:
    with pytest.raises(ConfigError) as e:
        from_dict(d)
    return e.value.problems


def test_every_example_config_loads_and_surveillance_yaml_is_one():
    sc = load("configs/surveillance.yaml")
    assert sc.surveillance is not None and sc.association.method == "jpda"
    sm = surveillance.build(sc)
    assert len(sm.truth_ids) >= 4 and sm.n_cells == 16
    # four or more targets enter at different scans, one leaves
    first = sm.exists.argmax(axis=1)
    assert len(set(first.tolist())) >= 4
    assert (~sm.exists[:, -1]).any()


@pytest.mark.parametrize(
    ("change", "path", "words"),
    [
        (
            lambda d: (
                d["surveillance"]["search"]["cells"].update(nx=8, ny=8)
                or d.update(sensors=[dict(SENSORS[0], max_range_m=3000.0), SENSORS[3]])
            ),
            "surveillance.search.cells",
            "outside every range-measuring sensor's coverage",
        ),
        (
            lambda d: d["surveillance"].update(
                births={
                    "rate": 0.1,
                    "regions": [{"min_m": [-500.0, 0.0], "max_m": [100.0, 2000.0]}],
                }
            ),
            "surveillance.births.regions[0]",
            "outside the area",
        ),
        (
            lambda d: d["surveillance"]["tracks"]["confirm"].update(m=4, n=3),
            "surveillance.tracks.confirm.m",
            "<= n",
        ),
        (
            lambda d: d["targets"][0].update(desired=[{"from_scan": 1, "diag": [1, 1, 1, 1]}]),
            "targets[0].desired",
            "truth only",
        ),
        (lambda d: d.update(fusion={"mode": "info"}), "fusion.mode", "central"),
        (lambda d: d["targets"][1].update(cued=True), "targets[1].cued", "scan 1"),
        (
            lambda d: d["targets"][1].update(leaves_at_scan=3),
            "targets[1].leaves_at_scan",
            "after appears_at_scan",
        ),
        (
            lambda d: d["surveillance"]["desired"]["tentative"].update(diag=[1, -1, 1, 1]),
            "surveillance.desired.tentative",
            "positive definite",
        ),
        (lambda d: d.update(sensors=[SENSORS[3]]), "sensors", "bearings alone"),
        (lambda d: d["allocation"].update(required=["P1"]), "allocation.required", "not with"),
        (lambda d: d["allocation"].update(search="exact")
         or d["surveillance"]["search"]["cells"].update(nx=8, ny=8),
         "allocation.search", "exact would weigh"),
        # accepted, and JPDA ran in its name (the summary said nearest)
        (lambda d: d["association"].update(method="nearest"), "association.method", "JPDA"),
    ],
)
def test_bad_values_are_refused_with_their_path(change, path, words):
    d = base()
    change(d)
    got = problems(d)
    assert any(p == path and words in m for p, m in got), got


def test_the_latency_grids_sweep_keys_are_refused_with_surveillance():
    """``sweep: {search_weight: [0, 20], delay_ms: [0, 100], loss: [0, 0.25]}`` swept λ alone
    and said nothing of the delays and losses (``check`` and ``sweep`` both exit 0)."""
    d = base(sweep={"search_weight": [0.0, 20.0], "delay_ms": [0, 100], "loss": [0.0, 0.25],
                    "late": ["drop"], "account_for_loss": [True], "seeds": 1})  # fmt: skip
    got = problems(d)
    assert [p for p, _ in got] == [
        "sweep.delay_ms", "sweep.loss", "sweep.account_for_loss", "sweep.late"
    ], got  # fmt: skip
    assert all("not with 'surveillance:'" in m for _, m in got), got
    # a normalised config spells out the defaults: accepted (its λ grid runs)
    d["sweep"] = {"search_weight": [0.0, 20.0], "seeds": 1}
    sc = from_dict(d)
    assert from_dict(normalised(sc)).sweep == sc.sweep


@pytest.mark.parametrize("mode", ["ci", "info"])
def test_a_fusion_centre_other_than_central_is_named_once(mode):
    """``fusion.mode: ci`` on a surveillance config gave three messages for one mistake: the
    surveillance refusal, the many-target one advising "central or info" (which surveillance
    refuses), and greedy's objection to a mode that is not the cause."""
    got = problems(base(fusion={"mode": mode}))
    assert len(got) == 1 and got[0][0] == "fusion.mode" and "only central" in got[0][1], got


def test_peer_mode_is_refused_as_peer_with_central_as_the_only_advice():
    """``--fusion peer`` on a surveillance config named the peer rule's default (``info:
    not with 'surveillance:'``) and advised ``central or info``, which surveillance refuses."""
    d = base(fusion={"mode": "peer"})
    d["allocation"]["search"] = "exact"  # greedy's own objection to peer aside
    got = [(p, m) for p, m in problems(d) if p == "fusion.mode"]
    assert got and all(m.startswith("peer") for _, m in got), got
    assert not any("info" in m for _, m in got), got
    assert any("use central)" in m for _, m in got), got


def test_jpda_and_appearing_targets_need_surveillance():
    d = base()
    del d["surveillance"]
    for t in d["targets"]:
        t["desired"] = [{"from_scan": 1, "diag": [100.0, 4.0, 100.0, 4.0]}]
    got = problems(d)
    assert any(p == "association.method" and "jpda needs" in m for p, m in got)
    assert any(p == "targets[1].appears_at_scan" for p, m in got)


def test_a_target_present_from_scan_1_has_the_many_target_truth_bit_for_bit():
    sc = from_dict(base())
    sm = surveillance.build(sc)
    tm = targets.build(sc)
    many = targets.truth_trajectories(tm)
    assert np.array_equal(sm.truth[0], many[0])  # A: appears at scan 1
    # C: exists at scans 2..11 only, starting from its configured state at scan 1's time
    assert sm.exists[2].tolist() == [1 <= k <= 10 for k in range(16)]
    assert np.isnan(sm.truth[2, 0]).all() and np.isnan(sm.truth[2, 11]).all()
    assert np.allclose(sm.truth[2, 1, [0, 2]], [6000.0 - 50.0, 16000.0 - 50.0], atol=5.0)


def test_no_search_no_clutter_one_cued_target_never_searches_nor_starts_a_track():
    """Spec §6: λ = 0, one target known at scan 1, no clutter."""
    d = base()
    d["targets"] = [dict(d["targets"][0], cued=True)]
    d["filter"] = {"initial_estimate": "truth"}  # known: the cue is the truth, with P0
    d["surveillance"]["search"]["weight"] = 0.0
    run = drive.run(from_dict(d), "spectral").run
    assert run.search_dwells.sum() == 0 and run.track_dwells.sum() > 0
    assert run.n_tracks_started == 0
    assert all(len(rows) == 1 and rows[0][0] == 1 for rows in run.tracks)
    assert (run.n_confirmed == 1).all() and run.n_false_tracks == 0


def test_pd_1_no_clutter_separated_targets_all_confirmed_without_false_tracks():
    """Spec §6: every target confirmed within n dwells of its first detection, no false
    track."""
    run = drive.run(from_dict(base()), "spectral").run
    assert np.isfinite(run.time_to_confirm).all(), run.time_to_confirm
    assert run.n_false_tracks == 0 and run.breaks == 0
    assert run.n_tracks_started == 3  # one per target, never a second


def test_a_baselines_budget_bounds_its_track_dwells_and_lambda_only_turns_search_on():
    """What the README says of the surveillance baselines: ``budget`` K bounds the dwells on
    tracks, and the sensors left off search (more than K on); λ > 0 of any size gives the same
    run (it scales only the search term of the recorded value), λ = 0 no search."""
    runs = {}
    for w in (0.0, 30.0, 3000.0):
        d = base()
        d["allocation"] = {"metrics": ["spectral"], "policy": "random", "budget": 1}
        d["surveillance"]["search"]["weight"] = w
        runs[w] = drive.run(from_dict(d), "spectral").run
    a, b = runs[30.0], runs[3000.0]
    assert (a.track_dwells <= 1).all() and a.enabled.sum(axis=1).max() > 1
    assert np.array_equal(a.enabled, b.enabled) and np.array_equal(a.search_dwells, b.search_dwells)
    assert np.array_equal(a.gospa, b.gospa) and not np.array_equal(a.value, b.value)
    assert runs[0.0].search_dwells.sum() == 0


def test_a_baselines_summary_names_its_policy_and_budget(tmp_path, capsys):
    """``summary.json`` of a surveillance run with ``policy: random`` named neither (the
    one-target and many-target runs' do: README); covariance control's adds nothing."""
    from covnet.cli.app import main

    d = base(scans=6)
    d["allocation"] = {"metrics": ["spectral"], "policy": "random", "budget": 2}
    cfg = tmp_path / "s.yaml"
    cfg.write_text(json.dumps(d))
    assert main(["run", str(cfg), "--out", str(tmp_path / "r"), "--no-figures"]) == 0
    s = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert (s["policy"], s["budget"]) == ("random", 2)
    cfg.write_text(json.dumps(base(scans=6)))
    assert main(["run", str(cfg), "--out", str(tmp_path / "cc"), "--no-figures"]) == 0
    s = json.loads((tmp_path / "cc" / "summary.json").read_text())
    assert "policy" not in s and "budget" not in s


def test_the_run_is_a_function_of_the_config_and_seed():
    sc = from_dict(base())
    a, b = drive.run(sc, "spectral").run, drive.run(sc, "spectral").run
    for f in ("gospa", "value", "u", "search_dwells"):
        assert np.array_equal(getattr(a, f), getattr(b, f))


def test_the_cells_mass_follows_growth_and_search():
    sc = from_dict(base())
    sm = surveillance.build(sc)
    c = SurveillanceCentre(sm)
    plan = c.decide(1, "spectral", frozenset())
    assert plan.tracks == () and plan.subset  # no track yet: only search
    searched = {plan.modes[j] for j in plan.subset}
    assert searched <= set(range(4))  # cells are columns T.. = 0.. with no track
    c.fuse(plan, {})  # nothing arrived: no search happened
    assert np.allclose(c.u, 0.5)
    # scan 2: the mass grew by the birth intensity; every dwell of scan 2 arrives empty
    plan = c.decide(2, "spectral", frozenset())
    assert np.allclose(plan.u, 0.52)
    empty = {sc_id: _Empty(sc_id) for sc_id in (sm.sensor_ids[j] for j in plan.subset)}
    c.fuse(plan, empty)
    miss = {c_: 1.0 for c_ in range(4)}
    for j in plan.subset:
        miss[plan.modes[j]] *= 1.0 - sm.tm.sensors[j].pd  # pd = 1: a searched cell is empty
    assert np.allclose(c.u, [0.52 * miss[c_] for c_ in range(4)])


class _Empty:
    def __init__(self, sid):
        self.sensor_id, self.z = sid, np.zeros((0, 2))


@pytest.mark.parametrize("metric", ["spectral", "kl"])
def test_the_allocator_with_no_track_and_only_cells_equals_the_reference(metric):
    rng = np.random.default_rng(3)
    N, C = 5, 3
    cells = CellTerms(
        rng.random(C) + 0.1, 4.0, 1.0 - rng.uniform(0.5, 0.95, (N, C)), rng.random((N, C)) < 0.8
    )
    z = np.zeros((0, 4, 4))
    args = (z, np.zeros((N, 0, 4, 4)), z, metric, [], np.zeros((N, 0), dtype=bool))
    a = allocate_assignments(*args, cells=cells)
    b = allocate_assignments_exhaustive(*args, cells=cells)
    assert a.assignment == b.assignment and a.value == b.value


def test_covnet_run_writes_the_surveillance_summary(tmp_path, capsys):
    from covnet.cli.app import main

    cfg = tmp_path / "s.yaml"
    import yaml

    cfg.write_text(yaml.safe_dump(base()))
    out = tmp_path / "run"
    assert main(["run", str(cfg), "--out", str(out), "--no-figures"]) == 0
    s = json.loads((out / "summary.json").read_text())
    blk = s["metrics"]["spectral"]
    assert s["truth_ids"] == ["A", "B", "C"]
    for key in (
        "gospa_mean",
        "gospa_missed",
        "time_to_confirm",
        "track_breaks",
        "id_switches",
        "search_share",
        "false_tracks",
    ):
        assert key in blk
    assert all(v is None or v >= 0 for v in blk["time_to_confirm"].values())
    # the association the centre ran, also when the key is left out (its default: pda)
    assert s["association"] == "jpda"
    d = base()
    del d["association"]
    cfg.write_text(yaml.safe_dump(d))
    assert main(["run", str(cfg), "--out", str(tmp_path / "run2"), "--no-figures"]) == 0
    assert json.loads((tmp_path / "run2" / "summary.json").read_text())["association"] == "jpda"
    assert math.isfinite(blk["gospa_mean"])
    assert "GOSPA" in capsys.readouterr().out


def test_the_live_view_draws_the_managers_tracks(tmp_path, capsys):
    """The Foxglove view of a surveillance scan: the present truths, every track K<id> against
    the confirmed P_d; covnet run --mcap says where the scene is recorded instead."""
    from covnet.cli.app import main
    from covnet.covariance_control.visual import Visual
    from covnet.runs.visual import ScanMessages
    from covnet.wire import messages as msg

    sc = from_dict(base())
    st = msg.Status(scan=3, t=3.0, enabled=("P1",), trace_P=10.0, trace_Pd=20.0, value=1.0,
                    t_sent_ns=0, episode=0, fused=("P1",))  # fmt: skip
    tr = msg.Truth(scan=3, t=3.0, target_ids=("A",), states=np.array([[3300.0, 100, 3000, 0]]))
    track = msg.Track(scan=3, t=3.0, x=np.array([3310.0, 90, 2990, 0]), P=np.eye(4) * 50,
                      t_sent_ns=0, episode=0, target_id="K1")  # fmt: skip
    view = Visual(sc).view(ScanMessages(0, 3, st, None, tr, {}, [track]))
    assert [t for t, _ in view.truths] == ["A"]
    (est,) = view.estimates
    assert est.id == "K1" and est.desired_xy is not None and est.f is not None
    cfg = tmp_path / "s.yaml"
    import yaml

    cfg.write_text(yaml.safe_dump(base()))
    rc = main(["run", str(cfg), "--out", str(tmp_path / "r"), "--no-figures", "--mcap"])
    assert rc == 2 and "covnet up" in capsys.readouterr().err


def test_auto_with_cells_is_exact_while_the_assignments_are_few_and_greedy_beyond():
    """search: auto on a surveillance scan: (T + C + 1)^n assignments decide between the exact
    allocator and the greedy search (cells of equal mass tie exactly: exact would enumerate
    the ties)."""
    from covnet.covariance_control import searches

    few = from_dict(base(allocation={"metrics": ["spectral"], "search": "auto"}))
    run = drive.run(few, "spectral").run  # 4 sensors, 4 cells: 5^4 assignments, exact
    assert np.isfinite(run.value).all() and run.n_tracks_started == 3
    d = base(allocation={"metrics": ["spectral"], "search": "auto"}, scans=3)
    d["targets"] = d["targets"][:1]
    d["surveillance"]["search"]["cells"] = {"nx": 8, "ny": 8}  # 65^3 > AUTO_MODES_MAX: greedy
    assert (64 + 1) ** 3 > searches.AUTO_MODES_MAX  # 3 sensors can search
    run = drive.run(from_dict(d), "spectral").run
    assert run.search_dwells.sum() > 0


def test_a_surveillance_scenario_without_targets_runs_the_search_alone(tmp_path, capsys):
    """``targets: []`` is a surveillance scenario (the config allows it: false tracks and the
    search over an empty area); its config check crashed on the targets' empty trajectories."""
    import warnings

    import yaml

    from covnet.cli.app import main

    d = base(targets=[])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every sensor covers a cell: nothing to warn about
        sc = from_dict(copy.deepcopy(d))
    assert not sc.targets
    cfg = tmp_path / "s.yaml"
    cfg.write_text(yaml.safe_dump(d))
    out = tmp_path / "run"
    assert main(["run", str(cfg), "--out", str(out), "--no-figures"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["truth_ids"] == []
    blk = s["metrics"]["spectral"]
    assert blk["false_tracks"] == 0  # no clutter, no target: no track at all
    assert blk["search_share"] == 1.0  # every dwell searches


def test_a_sensor_that_covers_only_search_cells_is_not_out_of_reach():
    """With a search grid a sensor can be allocated to the cells it covers: it is out of reach
    only if it covers neither a target's path nor a cell."""
    import warnings

    from covnet.covariance_control.config import ConfigWarning

    d = base()
    # P1 near the north-east cell's centre with a short range: no target's path, that cell
    d["sensors"][0].update(position_m=[16000.0, 16000.0], max_range_m=3000.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from_dict(copy.deepcopy(d))
    d["sensors"][0].update(position_m=[60000.0, 60000.0], max_range_m=1000.0)
    with pytest.warns(ConfigWarning, match=r"P1 never covers any target or search cell"):
        from_dict(d)


def test_a_dwell_without_clutter_that_sees_two_targets_is_fused(monkeypatch):
    """Spec §1: a dwell returns every present target in its window. Two targets 1.5 km apart
    in one cell, every sensor ``pd 1`` and no clutter: a dwell with two returns was refused as
    ``bad_measurement`` (the known-target rule "one return without clutter"), 24 honest dwells
    in 20 scans, and a target confirmed 12 scans late."""
    from covnet.covariance_control import surveillance_episode as se

    d = base(scans=20)
    d["targets"] = [
        {"id": "T1", "initial_position_m": [6000.0, 6000.0], "initial_velocity_mps": [50.0, 0.0]},
        {"id": "T2", "initial_position_m": [6000.0, 7500.0], "initial_velocity_mps": [50.0, 0.0]},
    ]
    refused, seen = [], []
    verdict = se.SurveillanceEpisode.verdict

    def counted(self, m, plan):
        v = verdict(self, m, plan)
        seen.append(np.asarray(m.z).shape[0])
        if v is not None:
            refused.append((plan.k, m.sensor_id, v))
        return v

    monkeypatch.setattr(se.SurveillanceEpisode, "verdict", counted)
    run = drive.run(from_dict(d), "spectral").run
    assert max(seen) >= 2  # the case arises
    assert refused == []
    assert np.isfinite(run.time_to_confirm).all() and (run.time_to_confirm <= 3).all()


def test_a_configured_target_that_flies_out_has_left_even_where_its_path_comes_back():
    """README: a target exists "only while it is inside the area: one that flies out leaves
    there, as a born target does". A target turning at 8 deg/s just inside the edge flew out at
    scan 4 and existed again from scan 22 (its deleted track then scored as a break)."""
    d = base(scans=40)
    d["targets"] = [
        {
            "id": "U1",
            "initial_position_m": [19800.0, 10000.0],
            "initial_velocity_mps": [60.0, 0.0],
            "manoeuvres": [
                {"kind": "turn", "from_scan": 1, "to_scan": 40, "turn_rate_deg_s": 8.0}
            ],
        },
        # one that flies in: it appears where it enters
        {"id": "I1", "initial_position_m": [-500.0, 5000.0], "initial_velocity_mps": [150.0, 0.0]},
    ]
    ex = surveillance.build(from_dict(d)).exists
    u1, i1 = ex[0], ex[1]
    assert u1[:3].all() and not u1[3:].any(), u1.astype(int)
    assert not i1[:3].any() and i1[4:].all(), i1.astype(int)
