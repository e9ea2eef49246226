"""The allocation policies (``allocation.policy``) through the kind's one engine: ``covnet run``,
a lockstep network run (the manager, sensors, world and recorder over one in-memory hub) and
``covnet replay`` agree bit for bit for every baseline; each policy does what its entry says
(budget, cyclic order, seeded draws); with ``targets:`` the network equals the in-process run;
the config refuses what an entry cannot do, naming the field."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from recipe_harness import PAPER, run_all_three
from test_multitarget_up import run_network, short_data

from covnet.cli.app import main
from covnet.config import ConfigError
from covnet.core.allocation.policy_registry import POLICIES
from covnet.core.metrics import METRICS
from covnet.covariance_control.config import from_dict, load
from covnet.covariance_control.model import build_model
from covnet.covariance_control.simulate import run_metric, run_targets
from covnet.runs.rundir import load_arrays

pytestmark = pytest.mark.integration

BASELINES = [name for name, p in POLICIES.items() if not p.delegates_to_search]
BUDGET = 3


def _config(tmp_path, policy, budget=BUDGET, scans=20, seed=None, **allocation):
    data = yaml.safe_load(PAPER.read_text())
    data["scans"] = scans
    if seed is not None:
        data["seed"] = seed
    al = {"metrics": ["abs_trace"], "policy": policy, **allocation}
    if budget is not None:
        al["budget"] = budget
    data.setdefault("allocation", {}).update(al)
    data.setdefault("network", {})["record"] = True
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / f"{policy}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("policy", BASELINES)
def test_every_policy_runs_alike_in_process_on_the_network_and_in_replay(tmp_path, policy):
    budget = None if policy == "all_on" else BUDGET
    cfg = _config(tmp_path, policy, budget=budget)
    run_all_three(cfg, tmp_path, "abs_trace")
    arrays = load_arrays(tmp_path / "run" / "arrays.npz")
    on = arrays["enabled.abs_trace"].sum(axis=1)
    if policy == "all_on":
        assert (on == 8).all()
    elif policy == "greedy_information":  # stops at K (information always grows here)
        assert (on == BUDGET).all(), on
    else:
        assert (on == BUDGET).all(), on
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["policy"] == policy and summary["budget"] == budget
    assert (
        json.loads((tmp_path / "run" / "config.json").read_text())["allocation"]["policy"] == policy
    )


def test_the_logged_value_is_the_objective_of_the_chosen_subset(tmp_path):
    """Oracle: a baseline's ``value`` is f(P_i, P_d) with P_i = (P⁻⁻¹ + Σ J_j)⁻¹ of its subset
    (the central rule's posterior covariance, up to rounding)."""
    sc = load(_config(tmp_path, "random"))
    model = build_model(sc)
    run = run_metric(sc, "abs_trace")
    for i in range(sc.scans):
        P_d = model.desired(i + 1)
        want = float(METRICS["abs_trace"](run.P_post[i], P_d))
        assert run.value[i] == pytest.approx(want, rel=1e-9, abs=1e-9)


def test_round_robin_takes_the_sensors_in_turn(tmp_path):
    sc = load(_config(tmp_path, "round_robin", scans=8))
    run = run_metric(sc, "abs_trace")
    sets = [tuple(np.flatnonzero(row)) for row in run.enabled]
    assert sets[:3] == [(0, 1, 2), (3, 4, 5), (0, 6, 7)], sets  # 8 sensors, K = 3, cyclic
    covered = set().union(*map(set, sets[:3]))
    assert covered == set(range(8))


def test_random_is_seeded(tmp_path):
    a = run_metric(load(_config(tmp_path / "a", "random", seed=5)), "abs_trace").enabled
    b = run_metric(load(_config(tmp_path / "b", "random", seed=5)), "abs_trace").enabled
    c = run_metric(load(_config(tmp_path / "c", "random", seed=6)), "abs_trace").enabled
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_a_policy_over_many_targets_on_the_network_equals_the_in_process_run():
    data = short_data()
    data["allocation"].update(policy="greedy_information", budget=6)
    sc = from_dict(data)
    result, _ = run_network(sc, ["abs_trace"])
    assert result.completed and result.error is None
    got = result.episodes["abs_trace"].as_run()
    ref = run_targets(sc, "abs_trace")
    np.testing.assert_array_equal(got.assignment, ref.assignment)
    np.testing.assert_array_equal(got.x_est, ref.x_est)
    assert (np.sum(ref.assignment >= 0, axis=1) <= 6).all()


@pytest.mark.parametrize(
    ("allocation", "field", "words"),
    [
        ({"policy": "random"}, "allocation.budget", "needs a budget K"),
        ({"policy": "covariance_control", "budget": 3}, "allocation.budget", "baseline"),
        ({"policy": "nearest"}, "allocation.policy", "round_robin"),
        ({"policy": "random", "budget": 3, "search": "greedy"}, "allocation.search", "only"),
        ({"policy": "all_on", "max_active": 3}, "allocation.max_active", "every available"),
    ],
)
def test_the_config_refuses_what_a_policy_cannot_do(tmp_path, allocation, field, words):
    data = yaml.safe_load(PAPER.read_text())
    data.setdefault("allocation", {}).update(allocation)
    with pytest.raises(ConfigError) as err:
        from_dict(data)
    text = str(err.value)
    assert field in text and words in text, text


def test_a_policy_needs_the_information_form(tmp_path):
    data = yaml.safe_load(PAPER.read_text())
    data["allocation"] = {"policy": "random", "budget": 3}
    data["fusion"] = {"mode": "ci"}
    with pytest.raises(ConfigError, match=r"allocation\.policy.*information form"):
        from_dict(data)


def test_the_cli_says_the_policy_and_mc_runs_it(tmp_path, capsys):
    cfg = _config(tmp_path, "uncertainty_reward", scans=12)
    assert (
        main(
            [
                "mc",
                str(cfg),
                "--trials",
                "2",
                "--workers",
                "1",
                "--no-figures",
                "--out",
                str(tmp_path / "mc"),
            ]
        )
        == 0
    )
    assert main(["check", str(cfg)]) == 0
    assert "uncertainty_reward" in capsys.readouterr().out
