"""``covnet bench`` on inputs it cannot take, and what it reports: a config of fewer than 8
sensors or with non-position sensors for the allocator bench, a bench network a config cannot
make, a disagreement with the reference (exit 1, as ``bench search``), and strict JSON lines."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

from covnet.cli.app import main
from covnet.covariance_control.commands import _agreed
from covnet.runs.rundir import json_line

ROOT = Path(__file__).resolve().parents[2]


def _three(tmp_path: Path) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "paper.yaml").read_text())
    data["sensors"] = data["sensors"][:3]
    path = tmp_path / "three.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["bench", "--config", "{three}", "--problems", "1", "--metric", "kl"], "--sensors 20"),
        (["bench", "--config", "{three}", "--sensors", "9", "--problems", "1"], "--sensors 9"),
        (["bench", "--config", "configs/multitarget.yaml", "--problems", "1"], "R1 is not one"),
        (
            ["bench", "up", "--config", "configs/multitarget.yaml", "--sensors", "5"],
            "--config, --sensors 5: sensor R1",
        ),
    ],
)
def test_inputs_the_bench_cannot_take_are_refused(tmp_path, capsys, monkeypatch, argv, needle):
    """Each ended in a traceback (ValueError); a radar or bearing sensor was taken for a
    position sensor of 1 m."""
    monkeypatch.chdir(ROOT)
    argv = [a.replace("{three}", str(_three(tmp_path))) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err, err


def test_a_disagreement_with_the_reference_fails_the_bench(capsys):
    """``bench multitarget`` printed ``agree_reference: false`` and exited 0."""
    assert _agreed([{"agree_reference": True}, {"exact_agree": None}]) == 0
    for key in ("agree_reference", "exact_agree", "reference_agree"):
        assert _agreed([{"agree_reference": True}, {key: False}]) == 1
        assert "disagreed with its reference" in capsys.readouterr().err


def test_json_lines_are_strict_json():
    """``bench search --json`` wrote ``NaN`` (and ``Infinity`` for --exact-cap inf)."""
    line = json_line({"a": math.nan, "b": [1.0, math.inf, -math.inf], "c": {"d": 2.5}, "e": "x"})
    assert json.loads(line, parse_constant=lambda c: pytest.fail(c)) == {
        "a": None, "b": [1.0, None, None], "c": {"d": 2.5}, "e": "x",
    }  # fmt: skip
