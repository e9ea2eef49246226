"""The kind registry (covnet.kinds) and the one config loader every kind goes through.

The four defects the copies between kinds had caused (issue 13), each for every kind:
``access_control`` without identities refused with its path; a relative ``credentials_file``
resolved against the config's folder; a recording's config hash the run's own; no wall-clock
field in a result file (tests/integration/test_golden.py)."""

from __future__ import annotations

import copy
import importlib
import json
from pathlib import Path

import pytest
import yaml

from covnet import kinds
from covnet.cli.app import main
from covnet.config import ConfigError
from covnet.errors import UsageError
from covnet.runs.recording import META_CONFIG, META_RUN, run_metadata

REPO = Path(__file__).resolve().parents[2]
CONFIGS = {
    "covariance_control": REPO / "configs" / "paper.yaml",
    "mobile": REPO / "configs" / "mobile.yaml",
    "passive": REPO / "configs" / "passive.yaml",
}


def _data(kind: str) -> dict:
    return yaml.safe_load(CONFIGS[kind].read_text())


def _write(tmp_path: Path, data: dict, name: str = "cfg.yaml") -> Path:
    p = tmp_path / name
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def test_every_shipped_config_is_of_its_kind():
    for name, path in CONFIGS.items():
        kind, cfg = kinds.load(path)
        assert kind.name == name == cfg.kind
        assert kinds.of(cfg) is kind


@pytest.mark.parametrize("name", sorted(kinds.REGISTRY))
def test_every_kind_provides_its_parts(name):
    """A registered kind: its options are run options, its three role modules exist with the
    entry points the role's __main__ calls, its episodes label the live status."""
    kind = kinds.get(name)
    assert kind.name == name and kind.title
    assert set(kind.options) <= set(kinds.OPTIONS) and "seed" in kind.options
    assert set(kind.roles) == {"manager", "sensor", "world"}
    for role, module in kind.roles.items():
        mod = importlib.import_module(module)
        assert callable(mod.run), module
        if role != "world":
            assert callable(mod.main), module
    _, cfg = kinds.load(CONFIGS[name])
    assert kind.episodes(cfg)
    assert kinds.config_hash(cfg) == kinds.config_hash(
        kind.from_dict(kind.normalised(cfg), "x", None)
    )


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_access_control_without_identities_is_refused_with_its_path(name, tmp_path, capsys):
    """Defect 1: for every kind, a path-precise error (covnet check: exit 2, no traceback)."""
    data = _data(name)
    data.setdefault("network", {})["security"] = {"access_control": True}
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as info:
        kinds.load(path)
    assert dict(info.value.problems)["network.security.access_control"].startswith(
        "needs node identities"
    )
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "network.security.access_control: needs node identities" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_relative_credentials_are_resolved_against_the_config_folder(name, tmp_path):
    """Defect 2: for every kind, ``credentials_file: creds.txt`` next to the config."""
    data = _data(name)
    data.setdefault("network", {})["security"] = {"credentials_file": "creds.txt"}
    path = _write(tmp_path / "sub", data)
    _, cfg = kinds.load(path)
    assert cfg.network.security.credentials_file == str((tmp_path / "sub" / "creds.txt").absolute())


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_a_recording_carries_the_runs_own_config_hash(name):
    """Defect 3: the recording's metadata holds the run's config and hash, for every kind."""
    _, cfg = kinds.load(CONFIGS[name])
    meta = run_metadata("r1", cfg)
    assert meta[META_RUN]["config_hash"] == kinds.config_hash(cfg)
    stored = json.loads(meta[META_CONFIG]["config.json"])
    assert stored == kinds.of(cfg).normalised(cfg)


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_the_network_table_is_checked_for_every_kind(name, tmp_path):
    data = _data(name)
    data.setdefault("network", {}).update(heartbeat_s=2.0, failure_timeout_s=1.0)
    data["network"]["latency"] = {"sensors": {"nobody": {}}}
    with pytest.raises(ConfigError) as info:
        kinds.load(_write(tmp_path, data))
    paths = dict(info.value.problems)
    assert paths["network.failure_timeout_s"] == "must be longer than network.heartbeat_s"
    assert paths["network.latency.sensors.nobody"] == "no sensor with id 'nobody'"


def test_options_are_changes_of_the_config():
    kind, cfg = kinds.load(CONFIGS["covariance_control"])
    out = kinds.apply_options(kind, cfg, "paper", seed=5, metric=["svd", "svd"], fusion="ci")
    assert (out.seed, out.allocation.metrics, out.fusion.mode) == (5, ("svd",), "ci")
    assert kinds.config_hash(out) != kinds.config_hash(cfg)
    assert kinds.apply_options(kind, cfg, "paper", seed=None, metric=[]) is cfg
    with pytest.raises(UsageError, match="--solver: a covariance-control scenario does not take"):
        kinds.apply_options(kind, cfg, "paper", solver="lp")
    with pytest.raises(UsageError, match="--metric: unknown metric 'nope'"):
        kinds.apply_options(kind, cfg, "paper", metric=["nope"])
    mobile, mcfg = kinds.load(CONFIGS["mobile"])
    assert kinds.apply_options(mobile, mcfg, "m", solver="milp").solver == "milp"
    with pytest.raises(UsageError, match="--seed: must be >= 0"):
        kinds.apply_options(mobile, mcfg, "m", seed=-1)


def test_a_command_a_kind_does_not_have_says_which_kinds_have_it():
    kind = kinds.get("passive")
    with pytest.raises(UsageError) as info:
        kinds.command(kind, "compare", "comparing fusion structures")
    assert "not defined for a passive scenario" in str(info.value)
    assert "covariance_control" in str(info.value)


def test_an_unknown_kind_names_the_choices(tmp_path):
    data = copy.deepcopy(_data("passive"))
    data["kind"] = "sonar"
    with pytest.raises(ConfigError, match=r"kind: unknown scenario kind 'sonar'; choose from"):
        kinds.load(_write(tmp_path, data))
