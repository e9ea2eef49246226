"""The many-target config (issue 16): ``targets:``, sensor models, coverage, detection, clutter,
association and OSPA; every bad value reported with its path; a sensor out of every target's
reach a warning; the paper configs unchanged."""

from __future__ import annotations

import copy
import warnings
from pathlib import Path

import pytest
import yaml

from covnet.config import ConfigError
from covnet.covariance_control.config import (
    ConfigWarning,
    config_hash,
    from_dict,
    load,
    normalised,
    reach_warnings,
)

ROOT = Path(__file__).resolve().parents[2]
MULTI = ROOT / "configs" / "multitarget.yaml"


@pytest.fixture()
def raw():
    return yaml.safe_load(MULTI.read_text())


@pytest.fixture()
def paper_raw(paper_path):
    return yaml.safe_load(paper_path.read_text())


def _problems(data) -> list[tuple[str, str]]:
    with pytest.raises(ConfigError) as info:
        from_dict(data, "test.yaml")
    return info.value.problems


def test_multitarget_loads():
    sc = load(MULTI)
    assert sc.multitarget
    assert sc.target_ids == ("T1", "T2", "T3")
    assert len(sc.sensors) == 12
    models = [s.model for s in sc.sensors]
    assert models.count("position") == models.count("range_bearing") == 4
    assert models.count("bearing") == 4
    assert all(s.pd == 0.9 and s.clutter_rate == 0.5 for s in sc.sensors)
    assert sc.targets[2].manoeuvres[0].kind == "turn"
    assert sc.targets[0].desired[1].weight == 2.0
    assert sc.association.method == "pda"
    assert sc.ospa.cutoff_m == 200.0


@pytest.mark.parametrize("name", ["paper.yaml", "latency.yaml"])
def test_paper_configs_normalise_without_the_new_keys(name):
    """A config without targets keeps its normalised form (and so its hash): none of the keys
    the many-target scenario added appear in it."""
    sc = load(ROOT / "configs" / name)
    assert not sc.multitarget
    data = normalised(sc)
    for key in ("targets", "association", "ospa"):
        assert key not in data
    assert "detection" not in data["allocation"]
    assert "max_per_target" not in data["allocation"]
    for s in data["sensors"]:
        assert set(s) == {"id", "sigma_x_m", "sigma_y_m", "rho"}
    assert config_hash(from_dict(data)) == config_hash(sc)


def test_hashes_of_the_shipped_paper_configs():
    """The hashes recorded in the golden results (tests/golden): unchanged by issue 16."""
    assert config_hash(load(ROOT / "configs" / "paper.yaml")) == "8759c41b742fbb0c"
    assert config_hash(load(ROOT / "configs" / "latency.yaml")) == "994046098c3ada55"


def test_multitarget_normalised_round_trip(raw):
    sc = from_dict(raw)
    data = normalised(sc)
    assert "target" not in data and "desired" not in data
    assert data["sensors"][4]["model"] == "range_bearing"
    again = from_dict(copy.deepcopy(data))
    assert config_hash(again) == config_hash(sc)
    assert normalised(again) == data


BAD = [
    ("rb-noise", lambda d: d["sensors"][4].pop("sigma_range_m"), "sensors[4].sigma_range_m",
     "missing required key"),
    ("bearing-pos", lambda d: d["sensors"][8].pop("position_m"), "sensors[8].position_m",
     "missing required key"),
    ("position-extra", lambda d: d["sensors"][0].update(sigma_bearing_mrad=1.0),
     "sensors[0].sigma_bearing_mrad", "only for"),
    ("bearing-xy", lambda d: d["sensors"][8].update(sigma_x_m=3.0), "sensors[8].sigma_x_m",
     "only for position"),
    ("pd", lambda d: d["sensors"][2].update(pd=1.5), "sensors[2].pd", "probability"),
    ("pd0", lambda d: d["sensors"][2].update(pd=0.0), "sensors[2].pd", "probability"),
    ("clutter", lambda d: d["sensors"][5].update(clutter_rate=-0.1), "sensors[5].clutter_rate",
     ">= 0"),
    ("range", lambda d: d["sensors"][5].update(max_range_m=0.0), "sensors[5].max_range_m",
     "> 0"),
    ("fov", lambda d: d["sensors"][5]["fov"].update(half_width_deg=200.0),
     "sensors[5].fov.half_width_deg", "(0, 180]"),
    ("model", lambda d: d["sensors"][5].update(model="sonar"), "sensors[5].model", "position"),
    ("sigma-b", lambda d: d["sensors"][9].update(sigma_bearing_mrad=-1.0),
     "sensors[9].sigma_bearing_mrad", "> 0"),
    ("target-dup", lambda d: d["targets"][1].update(id="T1"), "targets[1].id", "duplicate"),
    ("target-desired", lambda d: d["targets"][0]["desired"][1].update(from_scan=1),
     "targets[0].desired[1].from_scan", "increase"),
    ("target-desired-start", lambda d: d["targets"][2]["desired"][0].update(from_scan=3),
     "targets[2].desired[0].from_scan", "scan 1"),
    ("target-spd", lambda d: d["targets"][1]["desired"][0].update(diag=[1, -1, 1, 1]),
     "targets[1].desired[0]", "positive definite"),
    ("weight", lambda d: d["targets"][2].update(weight=0.0), "targets[2].weight", "> 0"),
    ("phase-weight", lambda d: d["targets"][0]["desired"][0].update(weight=-2.0),
     "targets[0].desired[0].weight", "> 0"),
    ("turn-rate", lambda d: d["targets"][2]["manoeuvres"][0].pop("turn_rate_deg_s"),
     "targets[2].manoeuvres[0].turn_rate_deg_s", "missing required key"),
    ("turn-accel", lambda d: d["targets"][2]["manoeuvres"][0].update(accel_mps2=[1.0, 0.0]),
     "targets[2].manoeuvres[0].accel_mps2", "not for a turn"),
    ("turn-end", lambda d: d["targets"][2]["manoeuvres"][0].update(to_scan=200),
     "targets[2].manoeuvres[0].to_scan", "beyond"),
    ("turn-order", lambda d: d["targets"][2]["manoeuvres"][0].update(to_scan=40),
     "targets[2].manoeuvres[0].to_scan", "after from_scan"),
    ("overlap", lambda d: d["targets"][2]["manoeuvres"].append(
        {"kind": "acceleration", "from_scan": 50, "to_scan": 70, "accel_mps2": [1.0, 0.0]}),
     "targets[2].manoeuvres[1]", "overlaps"),
    ("target-and-targets", lambda d: d.update(target={"initial_position_m": [0.0, 0.0]}),
     "target", "not with 'targets:'"),
    ("desired-and-targets", lambda d: d.update(desired=[{"from_scan": 1, "diag": [1, 1, 1, 1]}]),
     "desired", "not with 'targets:'"),
    ("no-targets", lambda d: d.update(targets=[]), "targets", "at least one"),
    ("gate", lambda d: d["association"].update(gate_probability=1.0),
     "association.gate_probability", "(0, 1)"),
    ("method", lambda d: d["association"].update(method="jpda"), "association.method", "pda"),
    ("window", lambda d: d["association"].update(clutter_window_sigma=0.0),
     "association.clutter_window_sigma", "> 0"),
    ("ospa-c", lambda d: d["ospa"].update(cutoff_m=-1.0), "ospa.cutoff_m", "> 0"),
    ("ospa-p", lambda d: d["ospa"].update(order=0.5), "ospa.order", ">= 1"),
    ("detection", lambda d: d["allocation"].update(detection="maybe"),
     "allocation.detection", "expected"),
    ("per-target", lambda d: d["allocation"].update(max_per_target=0),
     "allocation.max_per_target", "greater than or equal to 1"),
    # room for 3 of the 4 required: every scan turned every sensor off, exit 0
    ("per-target-required", lambda d: d["allocation"].update(
        max_per_target=1, required=[s["id"] for s in d["sensors"][:4]]),
     "allocation.max_per_target", "fewer than the 4 of allocation.required"),
    ("ci", lambda d: d.update(fusion={"mode": "ci"}), "fusion.mode", "ci is not available"),
    ("peer", lambda d: d.update(fusion={"mode": "peer"}), "fusion.mode", "peer is not available"),
    ("loss-aware", lambda d: d["allocation"].update(account_for_loss=True),
     "allocation.account_for_loss", "not available"),
]  # fmt: skip


@pytest.mark.parametrize("mutate, path, fragment", [c[1:] for c in BAD], ids=[c[0] for c in BAD])
def test_bad_value_reported_with_its_path(raw, mutate, path, fragment):
    mutate(raw)
    problems = _problems(raw)
    matching = [m for p, m in problems if p == path]
    assert matching, f"no problem at {path!r}; got {problems}"
    assert any(fragment in m for m in matching), matching


PAPER_BAD = [
    ("model", lambda d: d["sensors"][2].update(model="bearing", sigma_bearing_mrad=1.0,
                                               position_m=[0.0, 0.0]), "sensors[2].model"),
    ("pd", lambda d: d["sensors"][1].update(pd=0.9), "sensors[1].pd"),
    ("clutter", lambda d: d["sensors"][1].update(clutter_rate=0.5), "sensors[1].clutter_rate"),
    ("range", lambda d: d["sensors"][0].update(max_range_m=1e4, position_m=[0.0, 0.0]),
     "sensors[0].max_range_m"),
    ("association", lambda d: d.update(association={"method": "nearest"}), "association"),
    ("ospa", lambda d: d.update(ospa={"cutoff_m": 10.0}), "ospa"),
    ("detection", lambda d: d["allocation"].update(detection="ignore"), "allocation.detection"),
]  # fmt: skip


@pytest.mark.parametrize("mutate, path", [c[1:] for c in PAPER_BAD], ids=[c[0] for c in PAPER_BAD])
def test_many_target_keys_need_targets(paper_raw, mutate, path):
    """A config with the one ``target:`` is the paper's linear scenario: the new keys are
    refused there with a message that says they need ``targets:``."""
    mutate(paper_raw)
    problems = _problems(paper_raw)
    assert any(p == path and "targets" in m for p, m in problems), problems


def test_paper_config_needs_its_desired_schedule(paper_raw):
    del paper_raw["desired"]
    problems = _problems(paper_raw)
    assert ("desired", "missing required key (the desired-covariance schedule)") in problems


def test_every_problem_at_once(raw):
    raw["sensors"][4].pop("sigma_range_m")
    raw["targets"][2]["manoeuvres"][0].pop("turn_rate_deg_s")
    raw["association"]["gate_probability"] = 0.999
    raw["fusion"] = {"mode": "peer"}
    paths = {p for p, _ in _problems(raw)}
    assert {"sensors[4].sigma_range_m", "targets[2].manoeuvres[0].turn_rate_deg_s"} <= paths
    assert "fusion.mode" in paths


def test_a_sensor_out_of_every_targets_reach_is_a_warning(raw):
    raw["sensors"][0].update(position_m=[60000.0, 60000.0], max_range_m=1000.0)
    with pytest.warns(ConfigWarning, match=r"sensors\[0\]: P1 never covers any target"):
        sc = from_dict(raw)
    assert reach_warnings(sc)[0][0] == "sensors[0]"
    # a sector pointing away is out of reach too
    raw = yaml.safe_load(MULTI.read_text())
    raw["sensors"][4]["fov"] = {"center_deg": -135.0, "half_width_deg": 10.0}  # R1 looks away
    with pytest.warns(ConfigWarning, match=r"sensors\[4\]: R1 never covers"):
        from_dict(raw)


def test_a_config_warning_is_shown_at_every_load_at_the_callers_line(raw, tmp_path, capsys):
    """A config's warning was shown once per process (Python's "default" action remembers it
    in the registry of the module it names): a second ``api.load``, ``covnet check`` or
    ``covnet.cli.main(["check", ...])`` of the same config in one process said nothing, and
    the API's warning named ``covnet/kindkit.py``, not the caller's line.  Within one command
    or API call it is said once (its configs re-validated per option or seed say no more)."""
    from covnet.cli import api
    from covnet.cli.app import main

    raw["sensors"][0].update(position_m=[60000.0, 60000.0], max_range_m=1000.0)
    cfg = tmp_path / "far.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("default")  # Python's own action for a UserWarning
        for _ in range(2):
            api.load(cfg)  # the line the warnings name
        api.load(cfg, seed=3, metric="spectral")  # re-validated with its options: said once
    lines = [w.lineno for w in seen]
    assert [str(w.message).split(":")[0] for w in seen] == ["sensors[0]"] * 3
    assert {w.filename for w in seen} == {__file__}, [w.filename for w in seen]
    assert lines[0] == lines[1] != lines[2]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)  # the user's filters still decide
        api.load(cfg)
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # (pytest's own filter makes a warning an error)
        for _ in range(2):
            assert main(["check", str(cfg)]) == 0
            err = capsys.readouterr().err
            assert err.count("covnet: warning: sensors[0]: P1 never covers") == 1, err


def test_the_shipped_scenario_has_no_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load(MULTI)


def test_cli_check_prints_the_scenario(capsys):
    from covnet.cli.app import main

    assert main(["check", str(MULTI)]) == 0
    out = capsys.readouterr().out
    assert "targets:" in out and "model: range_bearing" in out and "clutter_rate: 0.5" in out


def test_a_key_of_another_model_names_the_sensors_model(raw):
    """The registry (issue 25): a sensor's keys are its model's; another model's key is
    refused naming the sensor's model and the models it belongs to."""
    raw["sensors"][0]["sigma_bearing_mrad"] = 1.0  # P1 is a position sensor
    raw["sensors"][8]["sigma_range_m"] = 20.0  # B1 a bearing one
    problems = _problems(raw)
    assert (
        "sensors[0].sigma_bearing_mrad",
        "not a field of model position (only for range_bearing, bearing sensors)",
    ) in problems
    assert (
        "sensors[8].sigma_range_m",
        "not a field of model bearing (only for range_bearing sensors)",
    ) in problems


def test_a_key_of_no_model_is_reported_with_every_other_problem(raw):
    raw["sensors"][4]["sigma_azimuth_mrad"] = 1.0
    raw["fusion"] = {"mode": "peer"}
    problems = dict(_problems(raw))
    assert problems["sensors[4].sigma_azimuth_mrad"].startswith(
        "unknown key: not a field of model range_bearing (its keys: sigma_range_m, "
        "sigma_bearing_mrad; "
        "every sensor's: id, model, position_m,"
    )
    assert "fusion.mode" in problems


def test_a_null_noise_key_of_another_model_is_as_if_absent(raw):
    """A sensor's normalised form lists the first three models' noise keys (null where not its
    model's), as before the registry: they load back."""
    raw["sensors"][0]["sigma_range_m"] = None
    assert config_hash(from_dict(raw)) == config_hash(load(MULTI))


def test_all_on_with_a_max_per_target_below_the_sensors_is_refused(raw, tmp_path, capsys):
    """``all_on`` puts every sensor on a target it covers; a cap per target below the sensors
    left a sensor with no open target: ``covnet check`` said 0, then every run, compare and mc
    stopped with a traceback (exit 1), with targets and in surveillance alike."""
    from covnet.cli.app import main

    raw["allocation"].update(policy="all_on", max_per_target=2)
    got = dict(_problems(raw))
    assert set(got) == {"allocation.max_per_target"}, got
    assert "all_on" in got["allocation.max_per_target"]
    assert "sensor (12) on" in got["allocation.max_per_target"]
    path = tmp_path / "allon.yaml"
    path.write_text(yaml.safe_dump(raw))
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "allocation.max_per_target: 2 with policy all_on" in err and "Traceback" not in err
    # a cap that no scan can reach stays allowed; max_per_target with any other policy too
    raw["allocation"]["max_per_target"] = 12
    from_dict(raw)
    raw["allocation"].update(policy="random", budget=4, max_per_target=1)
    from_dict(raw)
    surv = yaml.safe_load((ROOT / "configs" / "surveillance.yaml").read_text())
    surv["allocation"].update(policy="all_on", max_per_target=1)
    del surv["allocation"]["search"]
    assert [p for p, _ in _problems(surv)] == ["allocation.max_per_target"]
