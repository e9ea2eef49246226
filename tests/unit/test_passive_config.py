"""configs/passive.yaml: loading, defaults, and every kind of bad field reported with its path."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from covnet import kinds
from covnet.config import ConfigError
from covnet.passive.config import config_hash, from_dict, load

REPO = Path(__file__).resolve().parents[2]
PASSIVE = REPO / "configs" / "passive.yaml"


@pytest.fixture()
def raw():
    return yaml.safe_load(PASSIVE.read_text())


def _problems(data) -> list[tuple[str, str]]:
    with pytest.raises(ConfigError) as info:
        from_dict(data, "test.yaml")
    return info.value.problems


def test_passive_yaml_has_the_spec_setup():
    cfg = load(PASSIVE)
    np.testing.assert_array_equal(cfg.sensor_positions, [[0, 10, 0], [10, 0, 0], [0, 0, 0]])
    assert cfg.clutter.p_detect == 0.95 and cfg.clutter.rate_per_scan == 0.25
    assert cfg.clutter.window_rad == (0.1, 0.1)
    assert cfg.association.target_density_km3 == 0.025
    mc = cfg.montecarlo
    assert mc.formations == ("horizontal", "cross")
    assert mc.spacings_km == (0.5, 1.0, 2.0) and mc.sigmas_mrad == (1.0, 3.0, 5.0)
    assert mc.clutter == (False, True) and mc.trials == 100
    m = cfg.scene_model("horizontal", 2.0, 5.0, False)
    assert m.p_detect == 1.0 and m.clutter_rate == 0.0 and m.sigma_azimuth[0] == 5e-3
    p = cfg.assoc_params(cfg.scene_model(clutter=True))
    assert p.clutter_density == pytest.approx(25.0) and not p.complete_only
    assert kinds.load(PASSIVE)[0].name == "passive"
    assert kinds.load(REPO / "configs" / "paper.yaml")[0].name == "covariance_control"


def test_hash_is_stable_and_sensitive(raw):
    a = from_dict(copy.deepcopy(raw))
    assert config_hash(a) == config_hash(from_dict(copy.deepcopy(raw)))
    raw["association"]["method"] = "lr"
    assert config_hash(from_dict(raw)) != config_hash(a)


def test_scans_and_network_for_covnet_up(raw):
    """``scans`` (default 1) and ``network`` (defaults) stay out of the hash at their defaults;
    ``with_overrides`` re-validates."""
    from covnet.passive.config import normalised, with_overrides

    raw.pop("scans", None)
    a = from_dict(copy.deepcopy(raw))
    assert a.scans == 1 and a.sensor_ids == ("s1", "s2", "s3")
    assert config_hash(from_dict(copy.deepcopy(raw) | {"scans": 1})) == config_hash(a)
    assert "network" not in normalised(a) and "scans" not in normalised(a)
    b = with_overrides(a, scans=4, seed=9, network={"record": False})
    assert (b.scans, b.seed, b.network.record) == (4, 9, False)
    assert config_hash(b) != config_hash(a)
    with pytest.raises(ConfigError, match="scans"):
        with_overrides(a, scans=0)


def test_minimal_config_takes_the_spec_defaults(raw):
    cfg = from_dict({k: raw[k] for k in ("kind", "name", "seed", "sensors")})
    assert cfg.association.method == "cot" and cfg.association.gate_sigma == 3.0
    assert cfg.montecarlo.methods == ("cot", "lr", "milp", "greedy")


@pytest.mark.parametrize(
    ("case", "edit", "path", "fragment"),
    [
        ("no kind", lambda d: d.pop("kind"), "kind", "expected 'passive'"),
        ("wrong kind", lambda d: d.update(kind="paper"), "kind", "got 'paper'"),
        ("two sensors", lambda d: d["sensors"].pop(), "sensors", "exactly 3"),
        (
            "unknown key",
            lambda d: d["association"].update(methd="cot"),
            "association.methd",
            "unknown key",
        ),
        (
            "method",
            lambda d: d["association"].update(method="lp"),
            "association.method",
            "unknown method 'lp'",
        ),
        (
            "mc method",
            lambda d: d["montecarlo"].update(methods=["cot", "lp"]),
            "montecarlo.methods[1]",
            "choose from",
        ),
        (
            "p_detect",
            lambda d: d["clutter"].update(p_detect=1.5),
            "clutter.p_detect",
            "must be in (0, 1]",
        ),
        (
            "window",
            lambda d: d["clutter"].update(window_rad=[0.1, 0.0]),
            "clutter.window_rad",
            "(0, π)",
        ),
        (
            "string",
            lambda d: d["noise"].update(sigma_azimuth_mrad="3.0"),
            "noise.sigma_azimuth_mrad",
            "expected a number",
        ),
        (
            "sigma",
            lambda d: d["noise"].update(sigma_elevation_mrad=-1.0),
            "noise.sigma_elevation_mrad",
            "must be > 0",
        ),
        (
            "formation",
            lambda d: d["targets"].update(formation="diagonal"),
            "targets.formation",
            "'horizontal' or 'cross'",
        ),
        (
            "spacing",
            lambda d: d["montecarlo"].update(spacings_km=[0.5, 0.0]),
            "montecarlo.spacings_km[1]",
            "must be > 0",
        ),
        (
            "empty grid",
            lambda d: d["montecarlo"].update(sigmas_mrad=[]),
            "montecarlo.sigmas_mrad",
            "must not be empty",
        ),
        (
            "duplicate id",
            lambda d: d["sensors"][2].update(id="s1"),
            "sensors[2].id",
            "duplicate sensor id",
        ),
        (
            "same place",
            lambda d: d["sensors"][1].update(position_km=[0.0, 10.0, 1.0]),
            "sensors[1].position_km",
            "same horizontal position",
        ),
        (
            "position",
            lambda d: d["sensors"][0].update(position_km=[0.0, 1.0]),
            "sensors[0].position_km",
            "exactly 3",
        ),
        (
            "no clutter",
            lambda d: d["clutter"].update(rate_per_scan=0.0),
            "clutter.rate_per_scan",
            "must be > 0 when clutter.p_detect < 1",
        ),
        (
            "trials",
            lambda d: d["montecarlo"].update(trials=0),
            "montecarlo.trials",
            "greater than or equal to 1",
        ),
        (
            "bool",
            lambda d: d["montecarlo"].update(clutter=[0, 1]),
            "montecarlo.clutter[0]",
            "valid boolean",
        ),
    ],
    ids=lambda v: v if isinstance(v, str) else "",
)
def test_bad_fields_are_reported_with_their_path(raw, case, edit, path, fragment):
    edit(raw)
    problems = _problems(raw)
    assert any(p == path and fragment in msg for p, msg in problems), problems


def test_every_problem_is_reported_at_once(raw):
    raw["association"]["method"] = "nope"
    raw["sensors"][2]["id"] = "s1"
    paths = {p for p, _ in _problems(raw)}
    assert {"association.method", "sensors[2].id"} <= paths


def test_file_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("kind: passive\nsensors: [\n")
    with pytest.raises(ConfigError, match="not valid YAML: line"):
        load(bad)
    with pytest.raises(ConfigError, match="cannot read file"):
        load(tmp_path / "missing.yaml")
    top = tmp_path / "list.yaml"
    top.write_text("- 1\n")
    with pytest.raises(ConfigError, match="top level must be a mapping"):
        load(top)


def test_the_longest_list_the_manager_takes_is_the_longest_an_honest_sensor_sends():
    """A list of 256 rows passed the manager's check and stalled it for 20 s and 4 GB (cot) or
    ran it out of memory (lr); an honest sensor's list holds its 5 targets and Poisson(λ ≤ 50)
    false returns."""
    import numpy as np
    from scipy import stats

    from covnet.passive.config import MAX_PASSIVE_RATE
    from covnet.passive.network import MAX_LIST, usable_list
    from covnet.passive.scene import FORMATIONS, formation
    from covnet.wire import messages as msg

    targets = max(len(formation(f, 1.0, (5.0, 5.0), 1.0)) for f in FORMATIONS)
    honest = targets + int(stats.poisson.isf(1e-12, MAX_PASSIVE_RATE))
    assert honest <= MAX_LIST < 128

    def listing(n):
        z = np.zeros((n, 2))
        return msg.Measurement(scan=1, t=1.0, sensor_id="S1", z=z, R=np.eye(2) * 1e-5,
                               t_sent_ns=0, episode=0)  # fmt: skip

    assert usable_list(listing(honest)) and not usable_list(listing(128))
