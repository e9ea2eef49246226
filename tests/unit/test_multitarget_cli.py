"""``covnet run`` of a many-target config end to end (issue 16): the run directory, its result
keys, the figures, determinism for a seed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from covnet.cli.app import main
from covnet.runs.rundir import load_arrays

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def short_config(tmp_path_factory) -> Path:
    """configs/multitarget.yaml with 24 scans (the turn and the priority change moved into
    them) and one metric."""
    data = yaml.safe_load((ROOT / "configs" / "multitarget.yaml").read_text())
    data["scans"] = 24
    data["allocation"]["metrics"] = ["abs_trace"]
    data["targets"][2]["manoeuvres"][0].update(from_scan=8, to_scan=16)
    for t in data["targets"]:
        if len(t["desired"]) > 1:
            t["desired"][1]["from_scan"] = 13
    p = tmp_path_factory.mktemp("cfg") / "mt-short.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


@pytest.fixture(scope="module")
def run_dir(short_config, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "mt"
    assert main(["run", str(short_config), "--out", str(out)]) == 0
    return out


def test_run_directory_files(run_dir):
    for f in (
        "summary.json",
        "arrays.npz",
        "config.json",
        "run.json",
        "fig_scene.png",
        "fig_sensors_per_target.png",
        "fig_trace_per_target.png",
        "fig_ospa.png",
        "fig_assignment_raster.png",
    ):
        assert (run_dir / f).is_file(), f
    assert json.loads((run_dir / "run.json").read_text())["status"] == "completed"


def test_summary_keys(run_dir):
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["target_ids"] == ["T1", "T2", "T3"]
    assert s["sensor_models"][:5] == ["position"] * 4 + ["range_bearing"]
    blk = s["metrics"]["abs_trace"]
    K, N = 24, 12
    for key in ("allocation_rate", "mean_ospa", "mean_gospa", "subsets_evaluated_median"):
        assert isinstance(blk[key], float), key
    assert len(blk["ospa"]) == len(blk["gospa"]) == len(blk["value"]) == K
    assert all(0.0 <= o <= 200.0 for o in blk["ospa"])
    assert len(blk["assignments"]) == K
    assert set(blk["dwell_counts"]) == set(s["sensor_ids"])
    for sid, counts in blk["dwell_counts"].items():
        assert set(counts) == {"T1", "T2", "T3", "off"}
        assert sum(counts.values()) == K
        assert blk["usage"][sid] == K - counts["off"]
    on = sum(blk["sensors_per_scan"])
    assert blk["allocation_rate"] == pytest.approx(on / (K * N))
    for tid, t in blk["targets"].items():
        for key in ("rmse_position", "rmse_velocity", "mean_nees", "mean_nis"):
            assert isinstance(t[key], float), (tid, key)
        lo, hi = t["nees_band_95"]
        assert 0 < lo < 4 < hi
        nlo, nhi = t["nis_band_95"]
        assert 0 < nlo < t["nis_mean_dof"] < nhi
        for key in ("sensors_per_scan", "f", "trace_P", "trace_Pd"):
            assert len(t[key]) == K, (tid, key)
    assert sum(sum(t["sensors_per_scan"]) for t in blk["targets"].values()) == on


def test_arrays(run_dir):
    a = load_arrays(run_dir / "arrays.npz")
    assert a["truth"].shape == (3, 24, 4)
    assert a["P_d"].shape == (3, 24, 4, 4)
    assert a["assignment.abs_trace"].shape == (24, 12)
    assert a["x_est.abs_trace"].shape == (3, 24, 4)
    assert a["ospa.abs_trace"].shape == (24,)
    assert set(np.unique(a["assignment.abs_trace"])) <= {-1, 0, 1, 2}


def test_the_same_seed_gives_the_same_results(run_dir, short_config, tmp_path):
    out = tmp_path / "again"
    assert main(["run", str(short_config), "--out", str(out), "--no-figures"]) == 0
    assert (out / "summary.json").read_bytes() == (run_dir / "summary.json").read_bytes()
    a, b = load_arrays(run_dir / "arrays.npz"), load_arrays(out / "arrays.npz")
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    other = tmp_path / "seed"
    assert main(["run", str(short_config), "--out", str(other), "--seed", "5", "--no-figures"]) == 0
    s = json.loads((other / "summary.json").read_text())
    assert s["seed"] == 5
    assert s["metrics"] != json.loads((run_dir / "summary.json").read_text())["metrics"]


def test_plot_redraws(run_dir, capsys):
    (run_dir / "fig_ospa.png").unlink()
    assert main(["plot", str(run_dir)]) == 0
    assert (run_dir / "fig_ospa.png").is_file()


def test_refused_fusion_modes_name_what_is_missing(short_config, tmp_path, capsys):
    for mode, word in (("ci", "covariance intersection"), ("peer", "peer nodes")):
        assert (
            main(["run", str(short_config), "--fusion", mode, "--out", str(tmp_path / mode)]) == 2
        )
        err = capsys.readouterr().err
        assert "fusion.mode" in err and word in err


def test_a_config_warning_prints_as_one_line(capsys):
    from covnet.cli import app as cli
    from covnet.config import ConfigWarning

    w = ConfigWarning("sensors[0]", "P1 never covers any target")
    cli._show_warning(w, ConfigWarning, "x.py", 1)
    assert capsys.readouterr().err == "covnet: warning: sensors[0]: P1 never covers any target\n"


@pytest.mark.parametrize("command", ["compare", "sweep"])
def test_one_target_batches_refuse_many_targets(short_config, tmp_path, command, capsys):
    assert main([command, str(short_config), "--out", str(tmp_path / command)]) == 2
    assert "targets" in capsys.readouterr().err
