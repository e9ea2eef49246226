"""The README's recipe "Adding a fusion rule", followed to the letter: a rule is its class (here
:class:`recipe_entries.Naive`, naive track fusion that double-counts the common prior) and one
``FUSION_RULES`` line.  Registered so, in a temporary registry, it runs from ``covnet run``, in a
lockstep network (every node's loop over the in-memory bus, with a recorder) bit for bit as
``covnet run``, and ``covnet replay`` rebuilds that network run from its recording byte for
byte; a ``targets:`` config asking for it is refused in the rule's own words."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from nodethreads import run_recorded_network
from recipe_entries import Naive

from covnet.cli.app import main
from covnet.config import ConfigError
from covnet.covariance_control.config import from_dict, normalised, with_overrides
from covnet.covariance_control.fusion_rules import FUSION_RULES
from covnet.covariance_control.replay import replay_run
from covnet.runs.rundir import load_arrays

METRICS = ["spectral", "abs_trace"]


@pytest.fixture
def naive(monkeypatch):
    monkeypatch.setitem(FUSION_RULES, "naive", Naive)  # the recipe's one registry line


def test_a_new_rule_runs_everywhere_the_engine_runs(naive, paper, tmp_path):
    net = paper.network.model_dump() | {"record": True}
    short = with_overrides(paper, scans=25, network=net)
    data = normalised(short)
    sc = from_dict(
        data
        | {"fusion": {"mode": "naive"}, "allocation": data["allocation"] | {"metrics": METRICS}}
    )
    cfg = tmp_path / "naive.yaml"
    cfg.write_text(yaml.safe_dump(normalised(sc)))

    # covnet run
    run_dir = tmp_path / "run"
    argv = ["run", str(cfg), "--out", str(run_dir), "--no-figures"]
    assert main(argv) == 0
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["fusion"] == "naive"
    ran = load_arrays(run_dir / "arrays.npz")

    # a lockstep network: the manager, world, sensors and recorder loops over the bus
    net_dir = tmp_path / "network"
    result, _ = run_recorded_network(sc, METRICS, net_dir)
    assert result.completed and result.error is None
    for m in METRICS:
        got = result.episodes[m].as_run(len(sc.sensor_ids))
        np.testing.assert_array_equal(got.enabled, ran[f"enabled.{m}"])
        np.testing.assert_array_equal(got.x_est, ran[f"x_est.{m}"])  # bit for bit
        np.testing.assert_array_equal(got.P_post, ran[f"P_post.{m}"])

    # covnet replay of the network run
    report = replay_run(net_dir)
    assert report.identical, report.differences
    assert (net_dir / "replay" / "summary.json").read_bytes() == (
        net_dir / "summary.json"
    ).read_bytes()


def test_a_rule_without_a_many_target_form_is_refused_in_its_words(naive):
    data = yaml.safe_load((Path(__file__).parents[2] / "configs/multitarget.yaml").read_text())
    data["fusion"] = {"mode": "naive"}
    with pytest.raises(ConfigError) as err:
        from_dict(data)
    assert "fusion.mode" in str(err.value)
    assert "naive has no many-target form" in str(err.value)
