"""Resumable batches (issue 18): a real ``covnet sweep`` process interrupted half way by SIGINT
leaves its finished trials in ``OUT/trials``; the same command again skips them, says how many,
runs the rest, and its table equals an uninterrupted run's byte for byte."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import pytest
import yaml
from multiproc import REPO, CovnetProcess

pytestmark = [pytest.mark.integration]

GRID = {
    "delay_ms": [0, 200, 350],
    "loss": [0.0, 0.1],
    "modes": ["central", "ci"],
    "account_for_loss": [False],
    "seeds": 2,
}
TOTAL = 3 * 2 * 2 * 2


@pytest.fixture
def sweep_cfg(tmp_path: Path) -> Path:
    data = yaml.safe_load((REPO / "configs" / "latency.yaml").read_text())
    data["scans"] = 30
    data["sweep"] = GRID
    p = tmp_path / "sweep.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _trials(out: Path) -> int:
    return sum(1 for _ in (out / "trials").glob("*/*/*.json")) if (out / "trials").is_dir() else 0


def _sweep(cfg: Path, out: Path, *extra: str) -> CovnetProcess:
    return CovnetProcess(["sweep", str(cfg), "--out", str(out), "--no-figures", *extra])


@pytest.mark.timeout(300)
def test_sigint_half_way_then_resume_equals_an_uninterrupted_run(tmp_path, sweep_cfg):
    out = tmp_path / "cut"
    p = _sweep(sweep_cfg, out, "--workers", "2")
    try:
        deadline = time.monotonic() + 120
        while _trials(out) < TOTAL // 3 and time.monotonic() < deadline:
            assert p.proc.poll() is None, p.output()
            time.sleep(0.05)
        p.proc.send_signal(signal.SIGINT)  # to the command, as a Ctrl-C does
        rc = p.wait(timeout=30)
    finally:
        p.stop()
    kept = _trials(out)
    assert rc == 130, p.output()
    assert TOTAL // 3 <= kept < TOTAL, (kept, p.output())
    assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    assert "resumes" in p.output()
    for f in (out / "trials").rglob("*"):
        assert not f.name.endswith(".tmp"), f  # every trial file whole

    again = _sweep(sweep_cfg, out, "--workers", "2")
    try:
        assert again.wait(timeout=240) == 0, again.output()
    finally:
        again.stop()
    assert f"{kept} of {TOTAL} trials already done, skipped" in again.output()
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "completed"
    assert (info["runs_skipped"], info["runs_run"]) == (kept, TOTAL - kept)

    fresh = tmp_path / "whole"
    whole = _sweep(sweep_cfg, fresh, "--workers", "2")
    try:
        assert whole.wait(timeout=240) == 0, whole.output()
    finally:
        whole.stop()
    assert (out / "sweep.json").read_bytes() == (fresh / "sweep.json").read_bytes()
    assert (out / "sweep.csv").read_bytes() == (fresh / "sweep.csv").read_bytes()
    assert (out / "curves.npz").is_file()

    # a different config into the same directory is refused; the same one is not re-run
    other = sweep_cfg.with_name("other.yaml")
    data = yaml.safe_load(sweep_cfg.read_text())
    data["scans"] = 31
    other.write_text(yaml.safe_dump(data))
    refused = _sweep(other, out)
    try:
        assert refused.wait(timeout=60) == 2
    finally:
        refused.stop()
    assert "holds the trials of another batch" in refused.output()
    done = _sweep(sweep_cfg, out)
    try:
        assert done.wait(timeout=60) == 0
    finally:
        done.stop()
    assert f"{TOTAL} of {TOTAL} trials already done" in done.output()


MC_TRIALS = 6


@pytest.fixture
def mc_cfg(tmp_path: Path) -> Path:
    """configs/multitarget.yaml, shorter (a trial in about a second)."""
    data = yaml.safe_load((REPO / "configs" / "multitarget.yaml").read_text())
    data["scans"] = 12
    data["allocation"]["metrics"] = ["abs_trace"]
    data["targets"][2]["manoeuvres"][0].update(from_scan=4, to_scan=8)
    for t in data["targets"]:
        if len(t["desired"]) > 1:
            t["desired"][1]["from_scan"] = 7
    p = tmp_path / "mt.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _mc(cfg: Path, out: Path) -> CovnetProcess:
    return CovnetProcess(["mc", str(cfg), "--trials", str(MC_TRIALS), "--out", str(out)])


@pytest.mark.timeout(300)
def test_mc_interrupted_after_a_trial_then_resumed_equals_an_uninterrupted_run(tmp_path, mc_cfg):
    """covnet mc of a covariance-control config: the seeds done when a Ctrl-C comes stay in
    OUT/trials; the same command skips them, and its montecarlo.json is the uninterrupted
    run's, byte for byte."""
    out = tmp_path / "cut"
    p = CovnetProcess(
        ["mc", str(mc_cfg), "--trials", str(MC_TRIALS), "--out", str(out), "--workers", "1"]
    )
    try:
        deadline = time.monotonic() + 120
        while _trials(out) < 1 and time.monotonic() < deadline:
            assert p.proc.poll() is None, p.output()
            time.sleep(0.05)
        p.proc.send_signal(signal.SIGINT)
        rc = p.wait(timeout=30)
    finally:
        p.stop()
    kept = _trials(out)
    assert rc == 130, p.output()
    assert 1 <= kept < MC_TRIALS, (kept, p.output())
    assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    assert "resumes" in p.output()

    again = _mc(mc_cfg, out)
    try:
        assert again.wait(timeout=240) == 0, again.output()
    finally:
        again.stop()
    assert f"{kept} of {MC_TRIALS} trials already done, skipped" in again.output()
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "completed"
    assert (info["runs_skipped"], info["runs_run"]) == (kept, MC_TRIALS - kept)

    fresh = tmp_path / "whole"
    whole = _mc(mc_cfg, fresh)
    try:
        assert whole.wait(timeout=240) == 0, whole.output()
    finally:
        whole.stop()
    assert (out / "montecarlo.json").read_bytes() == (fresh / "montecarlo.json").read_bytes()
