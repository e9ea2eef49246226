"""``covnet up``'s launcher hung up or killed mid-run (hunt 11): a closed terminal or a dropped
ssh session sends SIGHUP, which had no handler, so the launcher died at once; its manager then
died on the broken pipe of its STATUS lines without writing anything, and a long run's every
scan was lost (the directory held ``live.json``, ``processes.json`` and a recording that
``covnet replay`` refused).  A hang-up now stops the run as SIGTERM does (exit 130, the scans
done written), and a manager whose launcher has gone stops and writes its results."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
import yaml
from multiproc import CovnetProcess, assert_nothing_left, pid_alive

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]


def _long(paper_path, tmp_path):
    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = 3000
    data["allocation"] = {**data["allocation"], "metrics": ["spectral"]}
    path = tmp_path / "long.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _started(cfg, out):
    p = CovnetProcess(["up", str(cfg), "--out", str(out), "--no-figures", "--realtime",
                       "--speed", "50"])  # fmt: skip
    assert p.wait_for("[manager] READY", timeout=60), p.output()
    assert p.wait_for(lambda s: s.startswith("[status]") or "STATUS" in s, timeout=30) or True
    time.sleep(0.5)  # a few scans done (the run takes 60 s: it is stopped long before its end)
    return p


def test_a_hang_up_stops_the_run_and_keeps_its_scans(tmp_path, paper_path):
    cfg, out = _long(paper_path, tmp_path), tmp_path / "hup"
    p = _started(cfg, out)
    try:
        os.kill(p.proc.pid, signal.SIGHUP)  # the launcher alone, as a terminal's hang-up
        rc = p.wait(timeout=60)
    finally:
        p.stop()
    assert rc == 130, p.output()
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "interrupted", info
    summary = json.loads((out / "summary.json").read_text())
    assert 0 < len(summary["metrics"]["spectral"]["subsets"]) < 3000
    assert not (out / "live.json").exists()
    assert_nothing_left(out)


def test_a_killed_launcher_leaves_the_manager_to_write_its_results(tmp_path, paper_path):
    cfg, out = _long(paper_path, tmp_path), tmp_path / "kill"
    p = _started(cfg, out)
    pids = json.loads((out / "processes.json").read_text())
    try:
        os.kill(p.proc.pid, signal.SIGKILL)
        p.wait(timeout=30)
        deadline = time.monotonic() + 60
        while pid_alive(pids["manager"]) and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        p.stop()
    assert not pid_alive(pids["manager"])
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "interrupted" and "launcher went away" in info["ended"], info
    summary = json.loads((out / "summary.json").read_text())
    assert 0 < len(summary["metrics"]["spectral"]["subsets"]) < 3000
    assert_nothing_left(out)
