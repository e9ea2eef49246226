"""Config mistakes refused at ``covnet check`` with their place, all at once (issue 26): a
many-target network beyond what its allocator can run, an allocation search ``targets:``
ignores, repeated YAML keys, and messages that say what is expected."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from covnet.cli.app import main
from covnet.config import ConfigError, read_yaml
from covnet.core.allocation.assignment import MAX_SENSORS
from covnet.covariance_control.config import from_dict

ROOT = Path(__file__).resolve().parents[2]
MULTI = ROOT / "configs" / "multitarget.yaml"
PAPER = ROOT / "configs" / "paper.yaml"


@pytest.fixture()
def multi():
    return yaml.safe_load(MULTI.read_text())


def _problems(data) -> list[tuple[str, str]]:
    with pytest.raises(ConfigError) as info:
        from_dict(data, "test.yaml")
    return info.value.problems


def _many_sensors(data: dict, n: int) -> dict:
    data = copy.deepcopy(data)
    base = data["sensors"][0]
    data["sensors"] = [{**base, "id": f"S{i}"} for i in range(n)]
    return data


# --------------------------------------------------------------------------------------------
# targets: what the many-target allocator can run
# --------------------------------------------------------------------------------------------


def test_more_sensors_than_exact_takes_is_refused_at_check(multi, tmp_path, capsys):
    """search: exact refuses, in its own words, what it cannot enumerate; auto is bounded
    beyond (no refusal)."""
    data = _many_sensors(multi, MAX_SENSORS + 1)
    data["allocation"]["search"] = "exact"
    p = tmp_path / "big.yaml"
    p.write_text(yaml.safe_dump(data))
    assert main(["check", str(p)]) == 2
    err = capsys.readouterr().err
    assert "sensors: " in err and f"at most {MAX_SENSORS}" in err and "Traceback" not in err
    assert "search exact is the exhaustive search's" in err
    from_dict(_many_sensors(multi, MAX_SENSORS + 1), "test.yaml")  # auto


def test_sensors_excluded_do_not_count_against_the_limit(multi):
    multi["allocation"]["search"] = "exact"
    data = _many_sensors(multi, MAX_SENSORS + 2)
    assert [p for p, _ in _problems(data)] == ["sensors"]
    data["allocation"]["excluded"] = ["S0", "S1"]
    sc = from_dict(data, "test.yaml")
    assert len(sc.sensors) == MAX_SENSORS + 2
    # exactly the limit passes
    from_dict(_many_sensors(multi, MAX_SENSORS), "test.yaml")


def test_a_paper_config_keeps_its_own_limit():
    """Without targets the allocation search has no 2^N tables: the limit is not its."""
    data = yaml.safe_load(PAPER.read_text())
    assert len(_many_sensors(data, MAX_SENSORS + 1)["sensors"]) > MAX_SENSORS
    from_dict(_many_sensors(data, MAX_SENSORS + 1), "test.yaml")


@pytest.mark.parametrize("search", ["bounded", "greedy"])
def test_targets_take_the_searches_at_scale(multi, search):
    multi["allocation"]["search"] = search
    assert from_dict(multi, "test.yaml").allocation.search == search


@pytest.mark.parametrize("search", ["exact", "auto"])
def test_the_searches_targets_use_are_accepted(multi, search):
    multi["allocation"]["search"] = search
    assert from_dict(multi, "test.yaml").allocation.search == search


def test_bounded_options_are_taken_by_the_searches_that_use_them(multi):
    """auto's bounded part and bounded read gap; exact refuses it in its own words."""
    multi["allocation"]["gap"] = 0.05
    from_dict(multi, "test.yaml")
    multi["allocation"]["search"] = "exact"
    [(path, msg)] = _problems(multi)
    assert path == "allocation.gap" and "only used with search" in msg


# --------------------------------------------------------------------------------------------
# duplicate YAML keys
# --------------------------------------------------------------------------------------------


def test_duplicate_keys_are_refused_with_their_lines(tmp_path, capsys):
    lines = PAPER.read_text().splitlines()
    at = lines.index("scans: 100")
    lines.insert(at + 1, "scans: 50")
    nested = lines.index("filter:")
    lines.insert(nested + 1, "  initial_estimate: truth")  # the file's own comes later
    p = tmp_path / "dup.yaml"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError) as info:
        read_yaml(p)
    msgs = [m for _, m in info.value.problems]
    assert len(msgs) == 2, msgs
    assert f"line {at + 2}" in msgs[0] and "'scans'" in msgs[0] and f"line {at + 1}" in msgs[0]
    assert "'initial_estimate' at line" in msgs[1] and f"line {nested + 4}" in msgs[1]
    assert f"first at line {nested + 2}" in msgs[1]
    assert main(["check", str(p)]) == 2
    assert "duplicate key 'scans'" in capsys.readouterr().err


def test_same_keys_in_different_mappings_are_fine(tmp_path):
    p = tmp_path / "ok.yaml"
    p.write_text("a: {x: 1, y: 2}\nb: {x: 1, y: 2}\nc: [{id: 1}, {id: 2}]\n")
    want = {"a": {"x": 1, "y": 2}, "b": {"x": 1, "y": 2}, "c": [{"id": 1}, {"id": 2}]}
    assert read_yaml(p) == want


def test_merge_keys_still_load(tmp_path):
    p = tmp_path / "merge.yaml"
    p.write_text("base: &b {x: 1, y: 2}\nover:\n  <<: *b\n  y: 3\n")
    assert read_yaml(p) == {"base": {"x": 1, "y": 2}, "over": {"x": 1, "y": 3}}


# --------------------------------------------------------------------------------------------
# messages
# --------------------------------------------------------------------------------------------


def test_a_fixed_length_says_exactly():
    data = yaml.safe_load(PAPER.read_text())
    data["desired"][0]["diag"] = [1.0, 2.0, 3.0]
    [(path, msg)] = _problems(data)
    assert path == "desired[0].diag"
    assert "exactly 4 items" in msg and "at least" not in msg, msg


def test_a_key_of_another_model_is_one_line(multi):
    multi["sensors"][0]["sigma_bearing_mrad"] = 2.0  # a position sensor
    [(path, msg)] = _problems(multi)
    assert path == "sensors[0].sigma_bearing_mrad"
    assert "range_bearing" in msg and "bearing" in msg and "position" in msg


def test_every_problem_at_once_across_the_stages(multi, tmp_path, capsys):
    multi["allocation"]["required"] = ["ZZ"]
    multi["allocation"]["excluded"] = [s["id"] for s in multi["sensors"]]
    multi["allocation"]["max_per_target"] = 0
    paths = [p for p, _ in _problems(multi)]
    assert paths == [
        "allocation.max_per_target",
        "allocation.required[0]",
        "allocation.excluded",
    ], paths
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(multi))
    assert main(["check", str(p)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 4


def test_a_structural_problem_does_not_also_report_its_own_field():
    """The later checks run on the config without the broken values: nothing they say about
    a broken value's place (or inside it) is a second line for the same mistake."""
    data = yaml.safe_load(PAPER.read_text())
    data["desired"][0]["diag"] = [1.0, 2.0, 3.0]  # desired[0] then has neither diag nor matrix
    data["sensors"][0]["sigma_x_m"] = "ten"  # the sensor then lacks sigma_x_m
    paths = [p for p, _ in _problems(data)]
    assert paths == ["sensors[0].sigma_x_m", "desired[0].diag"], paths


def test_the_config_knows_the_allocators_limit():
    from covnet.covariance_control.config import MULTITARGET_MAX_SENSORS

    assert MULTITARGET_MAX_SENSORS == MAX_SENSORS
