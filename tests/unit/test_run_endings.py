"""How ``covnet run`` ends when its last steps are cut short: a Ctrl-C between ``run.json``
and ``summary.json``, a reader of its output that goes away (``| head -1``), a closed stdout
(``>&-``). Each left a run directory that said something untrue, or a traceback."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from covnet.cli.app import main
from covnet.covariance_control import results

ROOT = Path(__file__).resolve().parents[2]
PAPER = str(ROOT / "configs" / "paper.yaml")


def test_a_ctrl_c_between_run_json_and_summary_json_is_not_a_complete_run(tmp_path, monkeypatch):
    """``run.json`` is written before ``summary.json``: a Ctrl-C between them was recorded as
    ``completed`` ("complete results") with no summary (``covnet plot`` then refused it)."""
    write = results.write_json

    def cut(path, obj):
        if path.name == "summary.json":
            raise KeyboardInterrupt
        write(path, obj)

    monkeypatch.setattr(results, "write_json", cut)
    out = tmp_path / "run"
    assert main(["run", PAPER, "--metric", "spectral", "--out", str(out), "--no-figures"]) == 130
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "interrupted" and "incomplete" in info["ended"]


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def test_covnet_run_piped_into_head_records_its_completed_run(tmp_path):
    """``covnet run ... | head -1``: exit 141 as a cut pipe, every file written, but
    ``run.json`` had no ``status``."""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "covnet", "run", PAPER, "--metric", "spectral", "--out",
           str(out), "--no-figures"]  # fmt: skip
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env()) as p:
        assert p.stdout is not None and p.stderr is not None
        p.stdout.readline()
        p.stdout.close()  # the reader goes
        err = p.stderr.read().decode()
        rc = p.wait(timeout=120)
    assert rc == 141, err
    assert "Traceback" not in err
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "completed", info
    assert (out / "summary.json").is_file()


def test_a_closed_stdout_is_dev_null_not_a_traceback(tmp_path):
    """``covnet check ... >&-`` and ``covnet run ... >&-``: Python leaves ``sys.stdout``
    ``None``; every print was a traceback (exit 1, nothing written)."""
    out = tmp_path / "run"
    run = ["run", PAPER, "--metric", "spectral", "--out", str(out), "--no-figures"]
    for args in (["check", PAPER], run):
        cmd = " ".join([sys.executable, "-m", "covnet", *args]) + " >&-"
        p = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, env=_env(),
                           timeout=120)  # fmt: skip
        assert p.returncode == 0, p.stderr
        assert "Traceback" not in p.stderr
    assert json.loads((out / "run.json").read_text())["status"] == "completed"


def test_an_ascii_stdout_escapes_a_name_it_cannot_encode(tmp_path):
    """``PYTHONIOENCODING=ascii`` (some CI and cron setups) and a run directory named
    ``Ünïcødé``: the summary's print was a ``UnicodeEncodeError`` after every result was
    written, exit 1, and ``run.json`` had no ``status`` (hunt 14).  The name is escaped."""
    out = tmp_path / "out Ünïcødé ✓"
    cmd = [sys.executable, "-m", "covnet", "run", PAPER, "--metric", "spectral", "--out",
           str(out), "--no-figures"]  # fmt: skip
    p = subprocess.run(cmd, capture_output=True, env={**_env(), "PYTHONIOENCODING": "ascii"},
                       timeout=120)  # fmt: skip
    assert p.returncode == 0, p.stderr.decode()
    assert b"Traceback" not in p.stderr
    assert b"out \\xdcn\\xefc\\xf8d\\xe9 \\u2713" in p.stdout, p.stdout.decode()
    assert json.loads((out / "run.json").read_text())["status"] == "completed"
