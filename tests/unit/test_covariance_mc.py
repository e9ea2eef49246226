"""``covnet mc`` of a covariance-control config (issue 16): seeds from the config's, means with
95 % intervals, the first seed is ``covnet run``'s."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

from covnet.cli.app import main
from covnet.covariance_control.montecarlo import interval

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def short_config(tmp_path_factory) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "multitarget.yaml").read_text())
    data["scans"] = 12
    data["allocation"]["metrics"] = ["abs_trace"]
    data["targets"][2]["manoeuvres"][0].update(from_scan=4, to_scan=8)
    for t in data["targets"]:
        if len(t["desired"]) > 1:
            t["desired"][1]["from_scan"] = 7
    p = tmp_path_factory.mktemp("cfg") / "mt-mc.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_interval_is_students():
    b = interval([1.0, 2.0, 3.0, 4.0])
    assert b["mean"] == 2.5 and b["n"] == 4
    half = 3.182446305284263 * b["std"] / 2.0  # t_{0.975, 3}
    assert b["ci95"] == pytest.approx([2.5 - half, 2.5 + half])
    assert interval([5.0])["ci95"] is None
    assert interval([None, 2.0])["n"] == 1


def test_mc_of_many_targets(short_config, tmp_path):
    out = tmp_path / "mc"
    assert (
        main(["mc", str(short_config), "--trials", "3", "--workers", "1", "--out", str(out)]) == 0
    )
    doc = json.loads((out / "montecarlo.json").read_text())
    assert doc["seeds"] == [2026, 2027, 2028]
    assert [r["seed"] for r in doc["per_seed"]] == doc["seeds"]
    blk = doc["aggregate"]["abs_trace"]
    for key in ("allocation_rate", "mean_ospa", "mean_gospa"):
        b = blk[key]
        assert b["n"] == 3 and b["ci95"][0] <= b["mean"] <= b["ci95"][1]
    assert len(blk["ospa_per_scan"]["mean"]) == 12
    for tid in ("T1", "T2", "T3"):
        t = blk["targets"][tid]
        assert t["rmse_position"]["ci95"][0] <= t["rmse_position"]["mean"]
        lo, hi = t["nees_batch"]["band_95"]
        assert lo < 4 < hi and t["nees_batch"]["values"] == 36
        assert t["nis_batch"]["values"] > 0
        assert len(t["trace_P_per_scan"]["mean"]) == 12
    assert (out / "montecarlo.png").is_file()
    assert json.loads((out / "run.json").read_text())["status"] == "completed"
    # trial 0 is covnet run's
    run = tmp_path / "run"
    assert main(["run", str(short_config), "--out", str(run), "--no-figures"]) == 0
    s = json.loads((run / "summary.json").read_text())["metrics"]["abs_trace"]
    row = doc["per_seed"][0]["metrics"]["abs_trace"]
    assert row["allocation_rate"] == s["allocation_rate"]
    assert row["targets"]["T2"]["rmse_position"] == s["targets"]["T2"]["rmse_position"]
    # covnet plot redraws it
    (out / "montecarlo.png").unlink()
    assert main(["plot", str(out)]) == 0 and (out / "montecarlo.png").is_file()


def _short_paper(paper_path: Path, tmp_path: Path, scans: int, **more) -> tuple[dict, Path]:
    """The paper config with ``scans`` scans, one metric, its P_d switch at half the run,
    written to ``tmp_path``: ``(data, path)``."""
    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = scans
    data["allocation"]["metrics"] = ["spectral"]
    data["desired"][1]["from_scan"] = scans // 2 + 1
    data |= more
    cfg = tmp_path / "p.yaml"
    cfg.write_text(yaml.safe_dump(data))
    return data, cfg


def test_mc_of_the_paper(paper_path, tmp_path):
    _, cfg = _short_paper(paper_path, tmp_path, 20)
    out = tmp_path / "mc"
    assert main(["mc", str(cfg), "--trials", "2", "--workers", "1", "--out", str(out)]) == 0
    doc = json.loads((out / "montecarlo.json").read_text())
    t = doc["aggregate"]["spectral"]["targets"]["T1"]
    assert t["rmse_position"]["n"] == 2 and math.isfinite(t["rmse_position"]["mean"])
    # the allocation does not depend on the seed (a linear filter's covariances do not)
    rates = [r["metrics"]["spectral"]["allocation_rate"] for r in doc["per_seed"]]
    assert rates[0] == rates[1]


def test_mc_resumes_after_a_change_of_its_evaluation_settings(paper_path, tmp_path, capsys):
    """The trials' key covered ``evaluation`` (which changes no trial), so changing only the
    burn-in refused the batch's own directory (exit 2, "holds the trials of another batch")."""
    data, cfg = _short_paper(paper_path, tmp_path, 6)
    out = tmp_path / "mc"
    argv = ["mc", str(cfg), "--trials", "2", "--workers", "1", "--out", str(out), "--no-figures"]
    assert main(argv) == 0
    first = (out / "montecarlo.json").read_bytes()
    data["evaluation"] = {"burn_in_scans": 2}
    cfg.write_text(yaml.safe_dump(data))
    capsys.readouterr()
    assert main(argv) == 0, capsys.readouterr().err
    assert json.loads((out / "montecarlo.json").read_text())["per_seed"] == json.loads(first)[
        "per_seed"
    ]


def test_mc_bad_trials(short_config, tmp_path, capsys):
    assert main(["mc", str(short_config), "--trials", "0", "--out", str(tmp_path / "x")]) == 2
    assert "--trials" in capsys.readouterr().err


def test_mc_takes_seed_metric_json_and_no_figures(short_config, tmp_path, capsys):
    """--seed (the first seed), --metric (only these metrics), --json (JSON Lines on stdout,
    one row per metric and target) and --no-figures, as sweep and compare take them."""
    data = yaml.safe_load(short_config.read_text())
    data["allocation"]["metrics"] = ["abs_trace", "spectral"]
    cfg = tmp_path / "two.yaml"
    cfg.write_text(yaml.safe_dump(data))
    out = tmp_path / "mc"
    argv = ["mc", str(cfg), "--trials", "2", "--workers", "1", "--out", str(out)]
    assert main([*argv, "--seed", "7", "--metric", "spectral", "--json", "--no-figures"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [(r["metric"], r["target"]) for r in rows] == [
        ("spectral", t) for t in ("T1", "T2", "T3")
    ]
    assert all(r["seeds"] == [7, 8] and r["rmse_position"]["n"] == 2 for r in rows)
    assert "lost_seeds" in rows[0] and "mean_ospa" in rows[0]
    doc = json.loads((out / "montecarlo.json").read_text())
    assert doc["seeds"] == [7, 8] and doc["metrics"] == ["spectral"]
    assert not (out / "montecarlo.png").exists()


def test_mc_options_a_kind_does_not_take_are_refused(tmp_path, capsys):
    mobile = ROOT / "configs" / "mobile.yaml"
    assert main(["mc", str(mobile), "--metric", "kl", "--out", str(tmp_path / "a")]) == 2
    assert "--metric: a mobile scenario does not take this option" in capsys.readouterr().err
    assert main(["mc", str(mobile), "--seed", "3", "--out", str(tmp_path / "b")]) == 2
    assert "--seed:" in capsys.readouterr().err


def test_compare_of_many_targets_points_to_mc_fusion_which_exists(short_config, tmp_path, capsys):
    assert main(["compare", str(short_config), "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "covnet mc --fusion central" in err and "covnet mc --fusion info" in err
    out = tmp_path / "mc"
    argv = ["mc", str(short_config), "--trials", "1", "--workers", "1", "--no-figures"]
    assert main([*argv, "--fusion", "info", "--out", str(out)]) == 0
    assert json.loads((out / "config.json").read_text())["fusion"]["mode"] == "info"
    assert main([*argv, "--fusion", "ci", "--out", str(tmp_path / "ci")]) == 2
    assert "fusion.mode: ci is not available with 'targets:'" in capsys.readouterr().err
