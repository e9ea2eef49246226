"""``covnet.cli.api`` (issue 18): run and sweep as functions returning result objects, numpy
arrays, ``to_frame()`` (pandas optional: a clear error without it), and the README's example,
run as it is written."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from covnet.cli import api
from covnet.config import ConfigError
from covnet.errors import UsageError

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


def test_to_frame_has_a_row_per_scan_whatever_the_other_arrays(paper_path):
    """The rows were the longest array's: with 5 scans and 8 sensors a paper run's frame was
    the 8 sensor names; a surveillance run's, its track rows."""
    pytest.importorskip("pandas")
    df = api.run(paper_path, metric="spectral", scans=5).to_frame()
    assert list(df["scan"]) == [1, 2, 3, 4, 5] and "nees.spectral" in df
    assert "x_est.spectral[2]" in df and "enabled.spectral[7]" in df and "sensor_ids" not in df
    r = api.run(REPO / "configs" / "surveillance.yaml", scans=100)
    df = r.to_frame()
    assert len(df) == 100 and "gospa.spectral" in df and "u.spectral[15]" in df
    assert np.array_equal(df["gospa.spectral"], r.arrays["gospa.spectral"])
    # a many-target (T, scans) array: a column per target
    r = api.RunResult(None, {"scans": 3}, {"nees.m": np.arange(6.0).reshape(2, 3)})
    df = r.to_frame()
    assert list(df["nees.m[1]"]) == [3.0, 4.0, 5.0] and len(df) == 3


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


def test_overrides_reach_list_items(paper_path):
    _, cfg = api.load(paper_path, sensors__0__rho=0.5, desired__1__from_scan=40)
    assert cfg.sensors[0].rho == 0.5 and cfg.desired[1].from_scan == 40
    with pytest.raises(ConfigError, match=r"sensors\[0\]\.rho: must be in \(-1, 1\)"):
        api.load(paper_path, sensors__0__rho=2.0)
    for bad, where in [
        ({"sensors__99__rho": 0.5}, "sensors__99__rho"),
        ({"sensors__x__rho": 0.5}, "sensors__x__rho"),
        ({"scans__x": 1}, "scans__x"),
    ]:
        with pytest.raises(ConfigError, match=where):
            api.load(paper_path, **bad)


def test_api_errors_name_the_argument_not_a_flag(paper_path):
    with pytest.raises(UsageError) as exc:
        api.load(paper_path, metric="nope")
    assert str(exc.value).startswith("metric: unknown metric 'nope'"), exc.value
    with pytest.raises(UsageError, match="^seed: must be >= 0"):
        api.load(paper_path, seed=-1)
    with pytest.raises(UsageError) as exc:
        api.load(REPO / "configs" / "mobile.yaml", metric="spectral")
    assert "--" not in str(exc.value) and str(exc.value).startswith("metric: "), exc.value
    with pytest.raises(UsageError, match="^metric: unknown metric 'nope'"):
        api.sweep(REPO / "configs" / "latency.yaml", metric="nope", seeds=1, workers=1)


def test_run_without_out_leaves_no_temporary_directory(paper_path, tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    r = api.run(paper_path, metric="spectral", scans=4)
    assert r.summary["scans"] == 4 and r.arrays["nees.spectral"].shape == (4,)
    assert r.out is None and list(tmp_path.iterdir()) == []
    kept = api.run(paper_path, metric="spectral", scans=4, keep=True)
    assert kept.out is not None and kept.out.parent == tmp_path
    assert (kept.out / "summary.json").is_file()
    shutil.rmtree(kept.out)
    # an interrupted or failed run leaves nothing either
    with pytest.raises(ConfigError):
        api.run(paper_path, scans=0)
    monkeypatch.setattr(api.kinds, "get", _failing_kind)
    with pytest.raises(RuntimeError, match="boom"):
        api.run(paper_path, scans=4)
    assert list(tmp_path.iterdir()) == []


def _failing_kind(name):
    class Kind:
        options: dict = {}

        @staticmethod
        def from_dict(data, source, base_dir):
            return data

        @staticmethod
        def normalised(cfg):
            return dict(cfg)

        @staticmethod
        def run(cfg, out, *, figures):
            (out / "half.json").write_text("{")
            raise RuntimeError("boom")

    return Kind()


_SHADOWED = """
import importlib.machinery, sys
from pathlib import Path

class Installed:
    # what an editable install's finder does: covnet's modules from the repository, consulted
    # after the path (where the folder named covnet/ was found first)
    @staticmethod
    def find_spec(name, path=None, target=None):
        if not name.startswith("covnet."):
            return None
        where = Path(REPO, *name.split(".")[:-1])
        return importlib.machinery.PathFinder.find_spec(name, [str(where)])

sys.meta_path.insert(sys.meta_path.index(importlib.machinery.PathFinder) + 1, Installed)
sys.path.insert(0, "")
try:
    exec(STATEMENT)
except ImportError as exc:
    print(exc)
    sys.exit(3)
"""


@pytest.mark.parametrize("statement", ["from covnet import api", "import covnet.cli.app"])
def test_a_folder_named_covnet_says_what_is_wrong(tmp_path, statement):
    """From the folder that holds a clone named ``covnet/``, Python imports that folder as a
    namespace package instead of the installed covnet."""
    (tmp_path / "covnet").mkdir()
    code = f"REPO = {str(REPO)!r}\nSTATEMENT = {statement!r}\n" + _SHADOWED
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    assert proc.returncode == 3, proc.stdout + proc.stderr
    msg = proc.stdout
    assert str(tmp_path / "covnet") in msg and "namespace package" in msg, msg
    assert "rename" in msg and "__version__" not in msg, msg


@pytest.mark.parametrize("config", [None, 42, ["configs/paper.yaml"]])
def test_a_config_of_another_type_is_named(config):
    """``api.run(None)`` ended in ``AttributeError: 'NoneType' object has no attribute
    'kind'``."""
    with pytest.raises(UsageError, match=r"config: a path, a mapping or a loaded config"):
        api.run(config)


def test_out_naming_a_file_is_refused_as_the_command_refuses_it(tmp_path, paper_path):
    """It ended in ``FileExistsError``, where ``covnet run --out FILE`` says what is wrong."""
    f = tmp_path / "notes.txt"
    f.write_text("mine\n")
    with pytest.raises(UsageError, match=r"out .*notes.txt: exists and is not a directory"):
        api.run(paper_path, out=f, scans=3)
    assert f.read_text() == "mine\n"


def test_out_follows_the_commands_rules(tmp_path, paper_path):
    """``api.run(out=DIR)`` wrote into a non-empty directory: an earlier run's summary and
    arrays replaced, its recording and figures left beside them (a mix of two runs), a user's
    files among the run's.  Now the command's ``--out`` rules: refused, or with ``force=True``
    an earlier covnet output emptied first."""
    earlier = tmp_path / "earlier"
    api.run(paper_path, out=earlier, scans=3, metric="kl")
    (earlier / "recording.mcap").write_bytes(b"an earlier network run's")
    before = sorted(p.name for p in earlier.iterdir())
    with pytest.raises(UsageError, match=r"out .*earlier: directory is not empty"):
        api.run(paper_path, out=earlier, scans=2, metric="kl")
    assert sorted(p.name for p in earlier.iterdir()) == before
    r = api.run(paper_path, out=earlier, scans=2, metric="kl", force=True)
    assert not (earlier / "recording.mcap").exists() and r.summary["scans"] == 2
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("x")
    with pytest.raises(UsageError, match=r"not an output of covnet"):
        api.run(paper_path, out=mine, scans=2, metric="kl", force=True)
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]


@pytest.mark.parametrize(
    "call,message",
    [
        (lambda p: api.run(p, metric=3), "metric: a metric name or a list of them, got 3"),
        (lambda p: api.run(p, seed="a"), "seed: an integer, got 'a'"),
        (lambda p: api.run(p, fusion=1), "fusion: a name, got 1"),
        (lambda p: api.run(p, out=5), "out: a path, got 5"),
        (lambda p: api.run(p, figures="no"), "figures: True or False, got 'no'"),
        (lambda p: api.sweep(p, workers="2"), "workers: an integer, got '2'"),
        (lambda p: api.sweep(p, metric=["kl", "svd"]), "metric: a metric name (a sweep runs"),
    ],
)
def test_wrong_argument_types_are_named(paper_path, call, message):
    """Each ended in a bare ``TypeError`` from deep inside (or, ``figures="no"``, counted as
    true)."""
    with pytest.raises(UsageError, match=re.escape(message)):
        call(paper_path)


def test_a_refused_option_lists_the_kinds_options(paper_path):
    """The API's message listed "(its options: none)"."""
    with pytest.raises(UsageError, match=re.escape("(its options: seed, metric, fusion)")):
        api.run(paper_path, solver="lp")


def test_to_frame_keeps_each_targets_estimate_and_truth():
    """A many-target run's ``(T, scans, 4)`` estimates and truths were left out of the frame
    (the README says a many-target array gives a column per target); so was every covariance."""
    pytest.importorskip("pandas")
    r = api.run(REPO / "configs" / "multitarget.yaml", metric="spectral")
    df = r.to_frame()
    x, truth, P = r.arrays["x_est.spectral"], r.arrays["truth"], r.arrays["P_post.spectral"]
    assert x.ndim == 3 and x.shape[1] == len(df)
    for t in range(x.shape[0]):
        for i in range(4):
            assert np.array_equal(df[f"x_est.spectral[{t}][{i}]"], x[t, :, i])
            assert np.array_equal(df[f"truth[{t}][{i}]"], truth[t, :, i], equal_nan=True)
    assert np.array_equal(df["P_post.spectral[2][0][1]"], P[2, :, 0, 1])
    one = api.run(REPO / "configs" / "paper.yaml", metric="kl", scans=4)
    assert np.array_equal(one.to_frame()["P_post.kl[1][3]"], one.arrays["P_post.kl"][:, 1, 3])


@pytest.mark.parametrize("name", ["paper", "mobile"])
def test_run_json_says_how_the_run_ended_as_the_commands_does(name, tmp_path):
    """``api.run(out=DIR)`` (and ``keep=True``) wrote a ``run.json`` without ``status``,
    ``ended``, ``blas_kernel`` or ``code``, which ``covnet run --out DIR`` writes (a failed API
    run had them, a completed one not)."""
    config = REPO / "configs" / f"{name}.yaml"
    for r in (
        api.run(config, out=tmp_path / "out", scans=3),
        api.run(config, keep=True, scans=3),
    ):
        assert r.out is not None
        info = json.loads((r.out / "run.json").read_text())
        assert (info["status"], info["ended"]) == ("completed", "every scan done")
        assert info["blas_kernel"] and info["code"]
    shutil.rmtree(r.out)


def test_run_silences_its_own_printout_not_the_programs(paper_path, capsys):
    """``api.run`` replaced the process's ``sys.stdout`` while it ran: what the program's
    other threads printed meanwhile was lost, and two calls in threads restored each other's
    stream out of order, leaving ``sys.stdout`` a dead ``StringIO`` (everything printed after
    them lost).  Now only the calling thread's printout (covnet's) is dropped."""
    import threading

    real = sys.stdout
    runs = [
        threading.Thread(target=lambda: api.run(paper_path, scans=30)),
        threading.Thread(target=lambda: api.run(REPO / "configs" / "mobile.yaml", scans=10)),
    ]
    for t in runs:
        t.start()
    ticks = 0
    while any(t.is_alive() for t in runs):
        print(f"tick {ticks}")
        ticks += 1
        for t in runs:
            t.join(0.01)
    print("after the runs")
    assert sys.stdout is real
    out = capsys.readouterr().out
    assert out.splitlines() == [*(f"tick {i}" for i in range(ticks)), "after the runs"], out
