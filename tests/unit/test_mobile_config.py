"""The mobile config: the scenario file, defaults, and every bad field reported with its path."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from covnet import kinds
from covnet.config import ConfigError
from covnet.mobile.config import config_hash, from_dict, load, with_overrides

MOBILE = Path(__file__).resolve().parents[2] / "configs" / "mobile.yaml"


@pytest.fixture()
def raw():
    return yaml.safe_load(MOBILE.read_text())


def _problems(data) -> list[tuple[str, str]]:
    with pytest.raises(ConfigError) as info:
        from_dict(data, "test.yaml")
    return info.value.problems


def test_scenario_file_has_the_spec_values():
    cfg = load(MOBILE)
    assert cfg.kind == "mobile" and cfg.scans == 100 and cfg.scan_period_s == 1.0
    assert cfg.target_ids == ("T1", "T2", "T3")
    assert cfg.targets[1].x0 == (250.0, -1.0, 60.0, 1.0)
    assert [s.speed_mps for s in cfg.sensors] == [3.0, 2.5, 3.0, 2.5]
    assert [s.sigma0_m for s in cfg.sensors] == [2.0, 2.5, 3.0, 2.0]
    assert [s.b0 for s in cfg.sensors] == [1.0, 0.8, 1.2, 0.9]
    assert cfg.sensors[2].start_m == (300.0, 300.0)
    assert (cfg.weights.alpha, cfg.weights.beta, cfg.weights.gamma) == (1.0, 0.1, 5.0)
    assert (cfg.detection.PD, cfg.detection.a, cfg.detection.b, cfg.detection.c) == (
        0.95, 1.0, 2.0, 0.0,
    )  # fmt: skip
    assert cfg.filter.P0_diag == (25.0, 0.25, 25.0, 0.25)
    assert cfg.solver == "lp" and cfg.dist_uses_velocity and cfg.trace_kind == "full"
    assert all(s.capacity is None for s in cfg.sensors)


def test_kind_identifies_the_file(tmp_path):
    """The kind registry decides the kind from one parse of the file; an unreadable file or
    bad YAML is a ConfigError naming it (not a guess)."""
    assert kinds.load(MOBILE)[0].name == "mobile"
    paper = Path(__file__).resolve().parents[2] / "configs" / "paper.yaml"
    assert kinds.load(paper)[0].name == "covariance_control"
    with pytest.raises(ConfigError, match="cannot read file"):
        kinds.load(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("kind: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        kinds.load(bad)
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("kind: radar\n")
    with pytest.raises(ConfigError, match="unknown scenario kind 'radar'"):
        kinds.load(unknown)


def test_hash_and_overrides(raw):
    a = from_dict(copy.deepcopy(raw))
    assert config_hash(a) == config_hash(from_dict(copy.deepcopy(raw)))
    b = with_overrides(a, seed=5, solver="milp")
    assert (b.seed, b.solver) == (5, "milp") and config_hash(b) != config_hash(a)
    assert with_overrides(a, seed=None).seed == a.seed
    with pytest.raises(ConfigError) as info:
        with_overrides(a, solver="simplex")
    assert info.value.problems[0][0] == "solver"
    assert "milp" in info.value.problems[0][1]


def _full_noise(sensor: dict, R0) -> None:
    del sensor["sigma0_m"]
    sensor["R0_m2"] = R0


BAD = [
    ("kind", lambda d: d.update(kind="paper"), "kind", "kind: mobile"),
    ("no-kind", lambda d: d.pop("kind"), "kind", "kind: mobile"),
    ("unknown-top", lambda d: d.update(scanz=3), "scanz", "unknown key"),
    (
        "unknown-sensor",
        lambda d: d["sensors"][2].update(sped=3.0),
        "sensors[2].sped",
        "unknown key",
    ),
    ("solver", lambda d: d.update(solver="simplex"), "solver", "choose from"),
    ("speed", lambda d: d["sensors"][1].update(speed_mps=-1.0), "sensors[1].speed_mps", ">= 0"),
    ("r_pd", lambda d: d["sensors"][0].update(r_pd_m=0.0), "sensors[0].r_pd_m", "> 0"),
    (
        "capacity",
        lambda d: d["sensors"][3].update(capacity=-1),
        "sensors[3].capacity",
        "greater than or equal to 0",
    ),  # fmt: skip
    ("capacity-float", lambda d: d["sensors"][3].update(capacity=1.5), "sensors[3].capacity", ""),
    ("pd", lambda d: d["detection"].update(PD=1.5), "detection.PD", "[0, 1]"),
    ("a", lambda d: d["detection"].update(a=0.0), "detection.a", "> 0"),
    ("weights", lambda d: d["weights"].update(gamma=-5.0), "weights.gamma", "> 0"),
    ("L", lambda d: d.update(noise_growth_L_m=[25.0, 0.0]), "noise_growth_L_m", "> 0"),
    ("L-len", lambda d: d.update(noise_growth_L_m=[25.0]), "noise_growth_L_m", "exactly 2"),
    ("x0-len", lambda d: d["targets"][0].update(x0=[1.0, 2.0]), "targets[0].x0", "exactly 4"),
    ("string-num", lambda d: d.update(scan_period_s="1.0"), "scan_period_s", "number"),
    ("bool-flag", lambda d: d.update(dist_uses_velocity="yes"), "dist_uses_velocity", "boolean"),
    ("trace", lambda d: d.update(trace_kind="diag"), "trace_kind", "full"),
    ("linking", lambda d: d["milp"].update(linking="medium"), "milp.linking", "strong"),
    ("gap", lambda d: d["milp"].update(rel_gap=1.0), "milp.rel_gap", "[0, 1)"),
    ("dup-target", lambda d: d["targets"][2].update(id="T1"), "targets[2].id", "duplicate"),
    ("dup-sensor", lambda d: d["sensors"][3].update(id="S1"), "sensors[3].id", "duplicate"),
    (
        "both-noise",
        lambda d: d["sensors"][0].update(R0_m2=[[4.0, 0.0], [0.0, 4.0]]),
        "sensors[0]",
        "exactly one",
    ),  # fmt: skip
    ("no-noise", lambda d: d["sensors"][0].pop("sigma0_m"), "sensors[0]", "exactly one"),
    (
        "R0-spd",
        lambda d: _full_noise(d["sensors"][1], [[1.0, 2.0], [2.0, 1.0]]),
        "sensors[1].R0_m2",
        "positive definite",
    ),  # fmt: skip
    ("no-targets", lambda d: d.update(targets=[]), "targets", "at least 1"),
    ("scans", lambda d: d.update(scans=0), "scans", "greater than or equal to 1"),
]


@pytest.mark.parametrize("mutate,path,fragment", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_fields_are_reported_with_their_path(raw, mutate, path, fragment):
    mutate(raw)
    problems = _problems(raw)
    paths = [p for p, _ in problems]
    assert path in paths, problems
    msg = dict(problems)[path]
    assert fragment in msg, problems


def test_a_full_R0_is_accepted(raw):
    _full_noise(raw["sensors"][1], [[4.0, 1.0], [1.0, 4.0]])
    cfg = from_dict(raw)
    assert cfg.sensors[1].R0().tolist() == [[4.0, 1.0], [1.0, 4.0]]
    assert cfg.sensors[0].R0().tolist() == [[4.0, 0.0], [0.0, 4.0]]


def test_all_problems_of_a_stage_are_reported_together(raw):
    raw["sensors"][0]["speed_mps"] = -1.0
    raw["detection"]["PD"] = 2.0
    raw["weights"]["extra"] = 1
    paths = {p for p, _ in _problems(raw)}
    assert {"sensors[0].speed_mps", "detection.PD", "weights.extra"} <= paths


def test_closed_form_with_capacity_is_refused(raw):
    raw["solver"] = "closed_form"
    raw["sensors"][0]["capacity"] = 1
    assert ("solver", "closed_form holds only without capacities; use lp (or lp_highs)") in (
        _problems(raw)
    )


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="cannot read file"):
        load(tmp_path / "nope.yaml")
    p = tmp_path / "broken.yaml"
    p.write_text("kind: mobile\nscans: [1,\n")
    with pytest.raises(ConfigError, match="not valid YAML: line"):
        load(p)
    p.write_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="mapping"):
        load(p)
