"""``covnet up ... | head -2``: the reader of the launcher's output goes after two lines.  The
launcher's line-reader thread printed a ``BrokenPipeError`` traceback; now the rest of the
output is dropped, the run goes on to its end (its files and recording whole: the replay is
identical) and the command exits 141, as ``covnet run | head`` does."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import yaml
from multiproc import REPO, assert_nothing_left

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]


def test_a_reader_that_goes_cuts_the_output_not_the_run(tmp_path, paper_path):
    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = 60
    data["allocation"]["metrics"] = ["spectral"]
    cfg = tmp_path / "p.yaml"
    cfg.write_text(yaml.safe_dump(data))
    out = tmp_path / "up"
    proc = subprocess.Popen(
        [sys.executable, "-m", "covnet", "up", str(cfg), "--out", str(out), "--no-figures"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        start_new_session=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert proc.stdout is not None
        for _ in range(2):
            assert proc.stdout.readline()
        proc.stdout.close()  # the reader goes (head -2)
        _, err = proc.communicate(timeout=150)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 141, err.decode()
    assert b"Traceback" not in err and b"BrokenPipe" not in err, err.decode()
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "completed" and info["scans_completed"] == {"spectral": 60}, info
    assert_nothing_left(out)
    from covnet.cli.app import main

    assert main(["replay", str(out)]) == 0
