"""Config loading: the paper file, defaults, and every kind of bad field reported with its path."""

from __future__ import annotations

import copy

import pytest
import yaml

from covnet.config import ConfigError
from covnet.covariance_control.config import config_hash, from_dict, load, normalised


@pytest.fixture()
def raw(paper_path):
    return yaml.safe_load(paper_path.read_text())


def _problems(data) -> list[tuple[str, str]]:
    with pytest.raises(ConfigError) as info:
        from_dict(data, "test.yaml")
    return info.value.problems


def test_paper_loads_with_spec_values(paper):
    assert paper.scans == 100
    assert paper.sensor_ids == tuple(f"S{i}" for i in range(1, 9))
    s1 = paper.sensors[0]
    assert (s1.sigma_x_m, s1.sigma_y_m, s1.rho) == (21.1, 8.2, 0.82)
    assert paper.desired[1].from_scan == 51
    assert paper.desired[1].diag == (7.0, 0.8, 7.0, 0.8)
    assert paper.allocation.metrics == ("spectral", "abs_trace", "svd")
    assert paper.filter.P0_diag == (1e4, 1e2, 1e4, 1e2)
    assert paper.target.initial_velocity_mps == (426.0, 0.0)


def test_defaults_fill_in(raw):
    data = copy.deepcopy(raw)
    for key in ("target", "filter", "allocation", "period_s"):
        del data[key]
    sc = from_dict(data)
    assert sc.target.initial_position_m == (0.0, 0.0)
    assert sc.filter.initial_estimate == "perturbed"
    assert sc.period_s == 1.0


def test_hash_is_stable_and_sensitive(raw):
    a = from_dict(copy.deepcopy(raw))
    b = from_dict(copy.deepcopy(raw))
    assert config_hash(a) == config_hash(b)
    raw["sensors"][0]["rho"] = 0.5
    assert config_hash(from_dict(raw)) != config_hash(a)
    assert normalised(a)["sensors"][0]["id"] == "S1"


BAD_CASES = [
    ("rho", lambda d: d["sensors"][3].update(rho=1.2), "sensors[3].rho", "must be in (-1, 1)"),
    (
        "sigma",
        lambda d: d["sensors"][0].update(sigma_x_m=-1.0),
        "sensors[0].sigma_x_m",
        "must be > 0",
    ),
    (
        "unknown-key",
        lambda d: d["sensors"][2].update(sigma_z=3),
        "sensors[2].sigma_z",
        "unknown key",
    ),
    ("top-unknown", lambda d: d.update(scanz=3), "scanz", "unknown key"),
    ("missing", lambda d: d["sensors"][1].pop("rho"), "sensors[1].rho", "missing required key"),
    ("type", lambda d: d.update(scans="many"), "scans", "valid integer"),
    ("bool-as-int", lambda d: d.update(seed=True), "seed", "valid integer"),
    ("nan", lambda d: d["sensors"][0].update(rho=float("nan")), "sensors[0].rho", "finite"),
    ("scans", lambda d: d.update(scans=0), "scans", "greater than or equal to 1"),
    ("period", lambda d: d.update(period_s=0.0), "period_s", "must be > 0"),
    ("p0", lambda d: d["filter"].update(P0_diag=[1, 1, -1, 1]), "filter.P0_diag", "> 0"),
    (
        "p0-len",
        lambda d: d["filter"].update(P0_diag=[1, 1, 1]),
        "filter.P0_diag",
        "exactly 4 items",
    ),
    (
        "estimate",
        lambda d: d["filter"].update(initial_estimate="guess"),
        "filter.initial_estimate",
        "perturbed",
    ),
    ("duplicate-id", lambda d: d["sensors"][4].update(id="S1"), "sensors[4].id", "duplicate"),
    (
        "metric",
        lambda d: d["allocation"].update(metrics=["spectral", "nuclear?"]),
        "allocation.metrics[1]",
        "unknown metric",
    ),
    (
        "required-id",
        lambda d: d["allocation"].update(required=["S9"]),
        "allocation.required[0]",
        "no sensor",
    ),
    (
        "req-and-excl",
        lambda d: d["allocation"].update(required=["S1"], excluded=["S1"]),
        "allocation",
        "both required and excluded",
    ),
    (
        "max-active",
        lambda d: d["allocation"].update(max_active=9),
        "allocation.max_active",
        "more than",
    ),
    (
        "max-active-req",
        lambda d: d["allocation"].update(max_active=1, required=["S1", "S2"]),
        "allocation.max_active",
        "required",
    ),
    (
        "desired-start",
        lambda d: d["desired"][0].update(from_scan=2),
        "desired[0].from_scan",
        "scan 1",
    ),
    (
        "desired-order",
        lambda d: d["desired"][1].update(from_scan=1),
        "desired[1].from_scan",
        "increase",
    ),
    (
        "desired-both",
        lambda d: d["desired"][1].update(matrix=[[1, 0, 0, 0]] * 4),
        "desired[1]",
        "exactly one",
    ),
    (
        "desired-spd",
        lambda d: d["desired"][1].update(diag=[7, -0.8, 7, 0.8]),
        "desired[1]",
        "positive definite",
    ),
    (
        "yaml-exponent",
        lambda d: d["filter"].update(P0_diag=["1.0e4", 100.0, 1e4, 100.0]),
        "filter.P0_diag[0]",
        "1.0e+4",
    ),
    ("no-sensors", lambda d: d.update(sensors=[]), "sensors", "at least 1"),
]


@pytest.mark.parametrize(
    "mutate, path, fragment", [c[1:] for c in BAD_CASES], ids=[c[0] for c in BAD_CASES]
)
def test_bad_field_reported_with_path(raw, mutate, path, fragment):
    mutate(raw)
    problems = _problems(raw)
    matching = [msg for p, msg in problems if p == path]
    assert matching, f"no problem at {path!r}; got {problems}"
    assert any(fragment in m for m in matching), matching


def test_every_problem_reported_at_once(raw):
    raw["sensors"][3]["rho"] = 3.0
    raw["sensors"][5]["sigma_y_m"] = 0
    raw["bogus"] = 1
    paths = {p for p, _ in _problems(raw)}
    assert {"sensors[3].rho", "sensors[5].sigma_y_m", "bogus"} <= paths


def test_problems_behind_others_are_reported_in_the_same_list(raw):
    """A bad value hid a repeated id (the id check runs once every sensor is valid), and a
    repeated id hid every check that spans fields (the whole sensor table was set aside):
    three rounds of fixes for one file.  Now one list."""
    raw["sensors"][0]["rho"] = 1.82
    raw["sensors"][1]["id"] = raw["sensors"][0]["id"]
    raw["desired"][0]["from_scan"] = 2
    raw["allocation"]["required"] = ["S9"]
    found = dict(_problems(raw))
    assert set(found) == {
        "sensors[0].rho", "sensors[1].id", "desired[0].from_scan", "allocation.required[0]"
    }, found  # fmt: skip
    assert "duplicate sensor id" in found["sensors[1].id"]
    assert "no sensor with id 'S9'" in found["allocation.required[0]"]


def test_a_repeated_id_is_a_structured_problem_the_repair_reads(raw):
    """The repair that keeps a repeated id's record (so the checks that span fields still see
    it) found the record by parsing the check's message text; it reads the problem's type and
    place now."""
    from covnet.covariance_control.config.scenario import Scenario
    from covnet.records import ValidationError

    raw["sensors"][4]["id"] = raw["sensors"][2]["id"]
    with pytest.raises(ValidationError) as exc:
        Scenario.model_validate(raw)
    (err,) = exc.value.errors()
    assert (err["loc"], err["type"]) == (("sensors", 4, "id"), "duplicate_id")
    raw["allocation"]["required"] = ["S9"]
    found = dict(_problems(raw))
    assert set(found) == {"sensors[4].id", "allocation.required[0]"}, found
    assert found["sensors[4].id"] == f"duplicate sensor id {raw['sensors'][2]['id']!r}"


def test_message_reads_path_colon_reason(raw):
    raw["sensors"][3]["rho"] = 1.5
    with pytest.raises(ConfigError) as info:
        from_dict(raw, "paper.yaml")
    assert "sensors[3].rho: must be in (-1, 1)" in str(info.value)


def test_not_a_mapping():
    assert _problems([1, 2])[0][1].startswith("the top level must be a mapping")


def test_load_bad_yaml_and_missing_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML: line"):
        load(bad)
    with pytest.raises(ConfigError, match="cannot read file"):
        load(tmp_path / "nope.yaml")


def test_a_budget_for_a_policy_that_takes_none_is_refused(raw):
    """all_on with allocation.budget: 4 ran every sensor while summary.json said budget 4."""
    raw["allocation"].update(policy="all_on", budget=4)
    found = dict(_problems(raw))
    assert found == {
        "allocation.budget": "policy all_on (every available sensor, every scan) takes no budget"
    }, found


def test_coverage_keys_without_targets_are_the_one_problem(raw):
    """A sensor with max_range_m on a one-target config was told to add position_m, then, once
    it had, that both need a 'targets:' list: only the root cause now."""
    raw["sensors"][3]["max_range_m"] = 1000.0
    found = dict(_problems(raw))
    assert set(found) == {"sensors[3].max_range_m"}, found
    assert found["sensors[3].max_range_m"].startswith("needs a 'targets:' list")


@pytest.mark.parametrize("policy", ["all_on", "random", "round_robin"])
def test_account_for_loss_with_a_policy_that_reads_no_information_is_refused(raw, policy):
    """``account_for_loss: true`` scales each sensor's information by its delivery probability;
    all_on, random and round_robin never read it: accepted, and their runs were those of false
    (the 24 such trials of a default sweep equal the other 24)."""
    raw["allocation"].update(policy=policy, account_for_loss=True)
    if policy != "all_on":
        raw["allocation"]["budget"] = 4
    found = dict(_problems(raw))
    assert set(found) == {"allocation.account_for_loss"}, found
    assert found["allocation.account_for_loss"].startswith(f"policy {policy} (")
    assert "reads no sensor information" in found["allocation.account_for_loss"]
    raw["allocation"]["policy"] = "greedy_information"  # reads J_j: accepted
    raw["allocation"]["budget"] = 4
    from_dict(raw)


@pytest.mark.parametrize("policy", ["all_on", "random", "round_robin", "greedy_information"])
def test_a_baseline_under_ci_is_refused_with_a_reason_true_for_it(raw, policy):
    """``random`` under ``fusion.mode: ci`` was refused because it "decides from the sensors'
    information J_j": all_on, random and round_robin never read J_j; the key and the modes
    allowed were right, the reason was not."""
    raw["allocation"]["policy"] = policy
    if policy != "all_on":
        raw["allocation"]["budget"] = 4
    raw["fusion"] = {"mode": "ci"}
    why = dict(_problems(raw))["allocation.policy"]
    ends = ("fusion.mode central or info); ci is not", "search over every subset; ci is not")
    assert why.endswith(ends), why
    assert ("J_j" in why) == (policy == "greedy_information"), why
    if policy != "greedy_information":
        assert why.startswith(f"a baseline such as {policy} is run only by a fusion centre in")
