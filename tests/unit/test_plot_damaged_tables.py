"""``covnet plot`` of a run directory whose result table was edited into another layout (a
key gone, text or null where a table was) ended in a traceback (KeyError, TypeError,
AttributeError: about 45 cases in a hunt over run, mc, sweep and compare directories); it is
the user's input: named, exit 2."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from covnet.cli.app import main
from tests.conftest import REPO


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("p") / "run"
    assert main(["run", str(REPO / "configs" / "paper.yaml"), "--no-figures", "--out", str(d)]) == 0
    return d


def _metrics_text(s):
    s["metrics"] = "x"


def _no_sensors_per_scan(s):
    del next(iter(s["metrics"].values()))["sensors_per_scan"]


def _null_metric(s):
    s["metrics"][next(iter(s["metrics"]))] = None


@pytest.mark.parametrize("damage", [_metrics_text, _no_sensors_per_scan, _null_metric])
def test_plot_of_an_edited_summary_is_a_usage_error(tmp_path, run_dir, capsys, damage):
    d = tmp_path / "copy"
    shutil.copytree(run_dir, d)
    summary = json.loads((d / "summary.json").read_text())
    damage(summary)
    (d / "summary.json").write_text(json.dumps(summary))
    assert main(["plot", str(d)]) == 2
    err = capsys.readouterr().err
    assert "does not have the layout covnet writes" in err and "Traceback" not in err


def test_plot_of_the_run_as_written_draws(tmp_path, run_dir):
    d = tmp_path / "copy"
    shutil.copytree(run_dir, d)
    assert main(["plot", str(d)]) == 0
