"""``covnet.api`` (issue 18): run and sweep as functions returning result objects, numpy
arrays, ``to_frame()`` (pandas optional: a clear error without it), and the README's example,
run as it is written."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from covnet import api
from covnet.config import ConfigError

REPO = Path(__file__).resolve().parents[2]


def _readme_example() -> str:
    text = (REPO / "README.md").read_text()
    m = re.search(r"<!-- api-example -->\s*```python\n(.*?)```", text, re.S)
    assert m, "README: no ```python block after <!-- api-example -->"
    return m.group(1)


def test_the_readme_example_runs_as_written():
    proc = subprocess.run(
        [sys.executable, "-c", _readme_example()],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert proc.returncode == 0, proc.stderr
    assert "rmse_steady_mean" in proc.stdout


def test_run_returns_the_summary_and_numpy_arrays(paper_path):
    r = api.run(paper_path, metric="spectral", scans=12, seed=3)
    assert r.summary["seed"] == 3 and r.summary["scans"] == 12
    assert isinstance(r.arrays["nees.spectral"], np.ndarray)
    assert r.arrays["nees.spectral"].shape == (12,)
    df = r.to_frame()
    assert len(df) == 12 and "nees.spectral" in df and "x_est.spectral[0]" in df
    with pytest.raises(ConfigError, match="scans"):
        api.run(paper_path, scans=-1)


def test_sweep_result(tmp_path):
    s = api.sweep(
        REPO / "configs" / "latency.yaml",
        seeds=2,
        scans=15,
        delay_ms=[0, 200],
        loss=[0.0],
        modes=["central"],
        account_for_loss=[False],
        workers=1,
        out=tmp_path / "sw",
    )
    assert len(s.rows) == 2 and s.points == [r["point"] for r in s.rows]
    e = s.errors(s.points[1])
    assert e["pos_err2"].shape == (2, 15) and list(e["seeds"]) == [2026, 2027]
    c = s.curves(s.points[1])
    assert np.all(c["rmse_lo"] <= c["rmse"]) and np.all(c["rmse"] <= c["rmse_hi"])
    assert list(s.to_frame()["delay_ms"]) == [0.0, 200.0]
    # resumable like the command: the same call again runs nothing
    again = api.sweep(
        REPO / "configs" / "latency.yaml", seeds=2, scans=15, delay_ms=[0, 200], loss=[0.0],
        modes=["central"], account_for_loss=[False], workers=1, out=tmp_path / "sw",
    )  # fmt: skip
    assert again.rows == s.rows


def test_to_frame_without_pandas_says_what_to_install(paper_path, monkeypatch):
    r = api.RunResult(Path("."), {"a": 1}, {"x": np.zeros(3)})
    monkeypatch.setitem(sys.modules, "pandas", None)
    with pytest.raises(ImportError, match="pip install pandas"):
        r.to_frame()
    assert r.arrays["x"].shape == (3,)  # the arrays are there without it
