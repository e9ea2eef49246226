"""A mobile run's ``summary.json`` and a Monte Carlo's ``montecarlo.json`` are strict JSON: a
rate over no scan (a target never assigned: ``miss_given_assigned``; the first half of a
one-scan run) was written as ``NaN``, which JSON does not have (``json.loads`` with a strict
``parse_constant``, like most other languages' parsers, refuses the file).  Now ``null``, and
the Monte Carlo's statistics are over the seeds where the rate is defined (``n`` says how
many)."""

from __future__ import annotations

import json

import pytest
import yaml

from covnet.cli.app import main
from tests.conftest import REPO


def _strict(path):
    def refuse(name):
        raise ValueError(f"{path}: {name} is not JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


def _config(tmp_path, **over):
    d = yaml.safe_load((REPO / "configs" / "mobile.yaml").read_text())
    d.update(over)
    p = tmp_path / "m.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


@pytest.mark.parametrize("case", ["one scan", "one sensor of capacity 1"])
def test_run_and_mc_files_are_strict_json(tmp_path, case):
    d = yaml.safe_load((REPO / "configs" / "mobile.yaml").read_text())
    if case == "one scan":
        cfg = _config(tmp_path, scans=1)
    else:
        sensor = {**d["sensors"][0], "capacity": 1}
        cfg = _config(tmp_path, scans=6, sensors=[sensor])
    run = tmp_path / "run"
    assert main(["run", str(cfg), "--out", str(run), "--no-figures"]) == 0
    s = _strict(run / "summary.json")
    blocks = [s["overall"], *s["targets"].values()]
    if case == "one scan":
        assert all(b["missed_detection_rate_first_half"] is None for b in blocks)
    else:
        assert any(b["miss_given_assigned"] is None for b in blocks)
    mc = tmp_path / "mc"
    assert main(["mc", str(cfg), "--trials", "2", "--out", str(mc), "--no-figures"]) == 0
    doc = _strict(mc / "montecarlo.json")
    assert doc  # strict JSON throughout
