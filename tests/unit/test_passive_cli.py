"""The passive commands: ``covnet mc`` end to end (tiny grid, process pool), ``covnet run`` (one
scene), ``covnet bench passive``, and their errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from covnet.cli.app import main
from covnet.core.passive import METHODS, Association
from covnet.errors import UsageError
from covnet.passive import bench
from covnet.passive.commands import bench_run, mc_run
from covnet.passive.config import load

REPO = Path(__file__).resolve().parents[2]
PASSIVE = REPO / "configs" / "passive.yaml"
ROW_KEYS = {
    "formation",
    "d_km",
    "sigma_mrad",
    "clutter",
    "method",
    "p",
    "precision",
    "exact_scan_rate",
    "median_time_s",
    "mean_candidates_azimuth",
    "mean_candidates_elevation",
    "sd_optimal_rate",
}


def _tiny(tmp_path: Path, **mc) -> Path:
    data = yaml.safe_load(PASSIVE.read_text())
    data["montecarlo"].update(
        {
            "trials": 2,
            "formations": ["cross"],
            "spacings_km": [1.0],
            "sigmas_mrad": [3.0],
            "clutter": [False, True],
            "workers": 2,
            **mc,
        }
    )
    p = tmp_path / "tiny.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_mc_cmd_end_to_end(tmp_path, capsys):
    cfg = _tiny(tmp_path)
    seen = []
    out = tmp_path / "mc"
    assert mc_run(load(cfg), out, None, lambda d, n, label: seen.append((d, n, label))) == 0
    assert [s[:2] for s in seen] == [(1, 2), (2, 2)]
    doc = json.loads((out / "results.json").read_text())
    assert doc["trials"] == 2 and doc["workers"] == 2 and doc["cells"] == 2
    rows = doc["rows"]
    assert len(rows) == 2 * len(METHODS)
    assert [(r["clutter"], r["method"]) for r in rows] == [
        (c, m) for c in (False, True) for m in ("cot", "lr", "milp", "greedy")
    ]
    for r in rows:
        assert ROW_KEYS <= set(r)
        assert 0.0 <= r["p"] <= 1.0 and r["median_time_s"] > 0
    cot = rows[0]
    assert cot["mean_candidates_azimuth"] >= cot["mean_candidates_elevation"] > 0
    lr = rows[1]
    assert lr["sd_optimal_rate"] is not None and cot["sd_optimal_rate"] is None
    table = (out / "results.md").read_text()
    assert table.count("| cross |") == len(rows)
    for f in ("fig_p_vs_d.png", "fig_time.png", "config.json"):
        assert (out / f).stat().st_size > 1000 or f == "config.json"
    printed = capsys.readouterr().out
    assert "results:" in printed and "cot" in printed


def test_mc_trials_override_and_a_user_method(tmp_path, monkeypatch, capsys):
    """A method added to the registry is selectable by name (in-process run: workers 1)."""

    def null(scan, params):
        return Association.empty(info={"n_tuples": 0})

    monkeypatch.setitem(METHODS, "null", null)
    cfg = _tiny(tmp_path, workers=1, methods=["null", "cot"], clutter=[False])
    out = tmp_path / "mc"
    assert mc_run(load(cfg), out, 3, False) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["trials"] == 3
    null_row = next(r for r in doc["rows"] if r["method"] == "null")
    assert null_row["p"] == 0.0 and null_row["exact_scan_rate"] == 0.0


def test_mc_errors(tmp_path, capsys):
    with pytest.raises(UsageError, match="--trials"):
        mc_run(load(PASSIVE), tmp_path / "x", 0, False)
    assert main(["mc", str(REPO / "configs" / "paper.yaml"), "--trials", "0", "--out",
                 str(tmp_path / "x")]) == 2  # fmt: skip
    assert "--trials: must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    f = tmp_path / "file"
    f.write_text("")
    with pytest.raises(UsageError, match="not a directory"):
        mc_run(load(_tiny(tmp_path)), f, 1, False)


def test_scene_cmd_writes_results_and_figure(tmp_path, capsys):
    out = tmp_path / "scene"
    assert main(["run", str(PASSIVE), "--out", str(out), "--seed", "5"]) == 0
    doc = json.loads((out / "association.json").read_text())
    assert doc["seed"] == 5 and doc["method"] == "cot"
    assert len(doc["measurements"]) == 3
    assert len(doc["positions_km"]) == len(doc["triples"]) == len(doc["correct"])
    targets = np.array(doc["targets_km"])
    for p, ok, t in zip(doc["positions_km"], doc["correct"], doc["target_of_triple"], strict=True):
        if ok:
            assert np.linalg.norm(np.array(p) - targets[t]) < 0.1
    assert (out / "scene.png").stat().st_size > 1000
    assert "time_s" not in doc  # wall-clock facts go to run.json
    assert json.loads((out / "run.json").read_text())["association_time_s"] > 0
    assert json.loads((out / "config.json").read_text())["seed"] == 5
    assert "run directory" in capsys.readouterr().out
    assert main(["run", str(PASSIVE), "--out", str(tmp_path / "neg"), "--seed", "-1"]) == 2
    assert "--seed: must be >= 0" in capsys.readouterr().err


def test_bench_cmd(monkeypatch, capsys):
    monkeypatch.setattr(bench, "DEFAULT_SCANS", 1)
    assert bench_run(json_out=True) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    rows, summary = lines[:-1], lines[-1]["summary"]
    assert {r["method"] for r in rows} == set(METHODS)
    assert summary["scenes"] == 24 and summary["scans_per_scene"] == 1
    assert summary["ratio_lr_over_cot_d_ge_1"] > 0
    assert bench_run(json_out=False) == 0
    text = capsys.readouterr().out
    assert "goal (cot >= 3x faster than lr for d >= 1 km)" in text


def test_covnet_cli_routes_passive_configs(tmp_path, capsys):
    """`covnet run` draws and associates one scan; `covnet mc` runs the protocol;
    `covnet up` runs it (tests/integration/test_passive_up.py) and refuses the options of
    the other kinds."""
    cfg = PASSIVE
    assert main(["run", str(cfg), "--out", str(tmp_path / "scene")]) == 0
    assert (tmp_path / "scene" / "association.json").is_file()
    assert main(["up", str(cfg), "--metric", "trace"]) == 2
    assert "--metric: a passive scenario does not take this option" in capsys.readouterr().err
    assert main(["up", str(cfg), "--solver", "lp"]) == 2
    assert "--solver: a passive scenario does not take this option" in capsys.readouterr().err


def test_mc_json_lines_and_no_figures(tmp_path, capsys):
    """covnet mc --json: stdout holds JSON Lines only (a row per cell and method);
    --no-figures draws nothing; --seed is the seed of the trials' streams."""
    out = tmp_path / "mc"
    argv = ["mc", str(_tiny(tmp_path)), "--out", str(out), "--json", "--no-figures"]
    assert main([*argv, "--seed", "5"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rows and all("method" in r for r in rows)
    assert not list(out.glob("*.png"))
    assert json.loads((out / "results.json").read_text())["seed"] == 5


def test_ci_width_says_how_many_trials_each_cell_ran(tmp_path, capsys):
    """With ``--ci-width`` the summary line, ``results.md`` and ``results.json`` said the first
    round's trial count ("6 trials per cell") where the cells ran 12 and 18."""
    data = yaml.safe_load(PASSIVE.read_text())
    data["montecarlo"].update(
        trials=6, formations=["cross"], spacings_km=[1.0], sigmas_mrad=[1.0, 3.0], methods=["cot"]
    )
    cfg = tmp_path / "p.yaml"
    cfg.write_text(yaml.safe_dump(data))
    out = tmp_path / "mc"
    argv = ["mc", str(cfg), "--out", str(out), "--workers", "1"]
    assert main([*argv, "--ci-width", "0.3", "--max-seeds", "18"]) == 0
    doc = json.loads((out / "results.json").read_text())
    ran = sorted({r["trials"] for r in doc["rows"]})
    assert len(ran) > 1, ran  # (the case: cells with different counts)
    text = f"{ran[0]}-{ran[-1]}"
    assert doc["trials_range"] == [ran[0], ran[-1]]
    assert f"x {text} trials in" in capsys.readouterr().out
    assert f"{text} trials per cell" in (out / "results.md").read_text().splitlines()[0]
