"""A full disk (or a read-only one) is named, not met as a bare ``OSError``.

A run that could not write a file said only ``covnet: error: No space left on device`` (a
failed ``write()`` names no file), left ``run.json`` without a ``status``, and a node of
``covnet up`` printed a traceback.  Now the error names the file, ``run.json`` says ``failed``
(or the message says it could not), no temporary file stays, and a node prints one line.
``covnet export --out`` and ``covnet plot`` on a read-only file system are refused before they
work (exit 2, naming ``--out`` or the directory), as the README says of every ``--out``.

The deterministic tests make the writer fail (``OSError(ENOSPC)`` at a chosen file); the
``real_fs`` ones mount a small tmpfs (root only: skipped with the reason elsewhere)."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import matplotlib.figure
import pytest
import yaml

from covnet.cli.app import main
from covnet.processes.process import guarded
from covnet.runs import rundir
from covnet.runs.recording import RecordingWriter
from tests.conftest import PAPER

FULL = "No space left on device"


def _enospc() -> OSError:
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as write() raises it: no file


@pytest.fixture
def paper5(tmp_path) -> Path:
    data = yaml.safe_load(PAPER.read_text())
    data["scans"] = 5
    cfg = tmp_path / "paper5.yaml"
    cfg.write_text(yaml.safe_dump(data))
    return cfg


@pytest.fixture
def disk_full_at(monkeypatch):
    """``disk_full_at(*names)``: from now on, writing a file of one of ``names`` through
    :func:`covnet.runs.rundir.atomic_write` / ``write_npz`` fails as a full disk does (the
    ``write()`` raises ``ENOSPC``; the temporary file is the writer's own)."""
    real = rundir._temporary_beside

    class Full:
        def __init__(self, fh):
            self._fh = fh

        def write(self, data):
            raise _enospc()

        def __getattr__(self, name):
            return getattr(self._fh, name)

    def arm(*names: str) -> None:
        @contextlib.contextmanager
        def beside(path: Path) -> Iterator:
            with real(path) as (fh, tmp):
                yield (Full(fh) if path.name in names else fh), tmp

        monkeypatch.setattr(rundir, "_temporary_beside", beside)

    return arm


def _one_error_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("covnet: error:")]
    assert len(lines) == 1, err
    return lines[0]


def _no_temporary_files(out: Path) -> None:
    left = [p.name for p in out.rglob("*") if ".tmp" in p.name]
    assert left == [], left


def test_a_file_that_cannot_be_written_is_named_and_run_json_says_failed(
    paper5, tmp_path, capsys, disk_full_at
):
    out = tmp_path / "out"
    disk_full_at("summary.json")
    assert main(["run", str(paper5), "--out", str(out), "--no-figures"]) == 1
    line = _one_error_line(capsys.readouterr().err)
    assert line == f"covnet: error: {out / 'summary.json'}: {FULL}", line
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "failed"
    assert f"{out / 'summary.json'}: {FULL}" in info["ended"]
    _no_temporary_files(out)


def test_when_run_json_cannot_be_written_either_the_message_says_so(
    paper5, tmp_path, capsys, disk_full_at
):
    out = tmp_path / "out"
    disk_full_at("summary.json", "run.json")
    assert main(["run", str(paper5), "--out", str(out), "--no-figures"]) == 1
    line = _one_error_line(capsys.readouterr().err)
    assert line.startswith(f"covnet: error: {out / 'summary.json'}: {FULL}; "), line
    assert f"{out / 'run.json'} does not say the command failed (not written: {FULL})" in line
    assert not (out / "run.json").exists()
    _no_temporary_files(out)


def test_a_figure_that_cannot_be_written_is_named(paper5, tmp_path, capsys, monkeypatch):
    def full(fig, *args, **kwargs):
        raise _enospc()

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", full)
    out = tmp_path / "out"
    assert main(["run", str(paper5), "--out", str(out)]) == 1
    line = _one_error_line(capsys.readouterr().err)
    assert line == f"covnet: error: {out / 'fig1_sensor_ellipses.png'}: {FULL}", line
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "failed" and "fig1_sensor_ellipses.png" in info["ended"]
    assert (out / "summary.json").is_file()  # the results before it are whole


def test_a_batch_on_a_full_disk_names_the_file_and_says_failed(
    paper5, tmp_path, capsys, disk_full_at
):
    out = tmp_path / "mc"
    disk_full_at("montecarlo.json")
    argv = ["mc", str(paper5), "--trials", "2", "--workers", "1", "--out", str(out)]
    assert main([*argv, "--no-figures"]) == 1
    line = _one_error_line(capsys.readouterr().err)
    assert line == f"covnet: error: {out / 'montecarlo.json'}: {FULL}", line
    assert json.loads((out / "run.json").read_text())["status"] == "failed"
    _no_temporary_files(out)
    disk_full_at()  # room again: the same command resumes, its trials kept
    assert main([*argv, "--no-figures"]) == 0
    assert "2 of 2 trials already done, skipped" in capsys.readouterr().err
    assert json.loads((out / "run.json").read_text())["status"] == "completed"


@pytest.mark.parametrize("named", [True, False])
def test_a_node_prints_one_line_for_a_file_it_cannot_write(capsys, named):
    def body() -> int:
        exc = _enospc()
        if named:
            exc.filename = "run/summary.json"
        raise exc

    assert guarded(body, "manager") == 1
    err = capsys.readouterr().err
    where = "run/summary.json: " if named else ""
    assert err == f"manager: error: {where}{FULL}\n", err


def test_a_recording_that_cannot_be_written_is_named(tmp_path):
    path = tmp_path / "recording.mcap"
    with pytest.raises(OSError) as exc_info, RecordingWriter(path, run_id="r"):
        raise _enospc()  # a write of the recording failing as on a full disk
    assert exc_info.value.filename == str(path)


# ---- export and plot on a read-only file system -------------------------------------------


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory) -> Path:
    data = yaml.safe_load(PAPER.read_text())
    data["scans"] = 4
    cfg = tmp_path_factory.mktemp("cfg") / "paper.yaml"
    cfg.write_text(yaml.safe_dump(data))
    out = tmp_path_factory.mktemp("runs") / "paper"
    assert main(["run", str(cfg), "--out", str(out), "--no-figures"]) == 0
    return out


@pytest.fixture
def read_only(monkeypatch):
    """Every directory reads as on a read-only file system to covnet's write check (root
    writes into a ``chmod 0555`` directory all the same)."""
    real = Path.write_bytes

    def write_bytes(self, data):
        if self.name.startswith(".covnet-write-check"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", write_bytes)


def test_export_to_a_read_only_folder_is_refused_before_it_works(
    paper_run, tmp_path, capsys, read_only
):
    target = tmp_path / "x.csv"
    assert main(["export", str(paper_run), "--out", str(target)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line == f"covnet: error: --out {target}: cannot write there (Read-only file system)"
    assert not target.exists()
    assert main(["export", str(paper_run)]) == 2  # the default: the run directory
    assert f"{paper_run} (the export's default folder: give --out" in capsys.readouterr().err
    assert main(["export", str(paper_run), "--out", "-"]) == 0  # stdout needs no folder


def test_plot_into_a_read_only_run_directory_is_refused_before_it_draws(
    paper_run, capsys, read_only
):
    assert main(["plot", str(paper_run)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line == (
        f"covnet: error: {paper_run} (covnet plot draws the figures into it): cannot write "
        "there (Read-only file system)"
    )
    assert not list(paper_run.glob("*.png"))


# ---- the same on real file systems (root: a small or read-only tmpfs) ------------------------


def test_a_run_on_a_real_full_disk(tmpfs, capsys):
    """100 kB: ``config.json`` and ``arrays.npz`` fit, the paper run's ``summary.json`` not."""
    out = tmpfs("small", "size=100k") / "o"
    assert main(["run", str(PAPER), "--out", str(out), "--no-figures"]) == 1
    line = _one_error_line(capsys.readouterr().err)
    assert line.startswith(f"covnet: error: {out}/"), line
    assert f": {FULL}" in line
    if "run.json does not say" not in line:
        assert json.loads((out / "run.json").read_text())["status"] == "failed"
    _no_temporary_files(out)


def test_export_and_plot_on_a_real_read_only_file_system(paper_run, tmpfs, capsys):
    ro = tmpfs("ro", "size=1m,ro")
    assert main(["export", str(paper_run), "--out", str(ro / "x.csv")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    want = f"--out {ro / 'x.csv'}: cannot write there (Read-only file system)"
    assert line == f"covnet: error: {want}", line
    copy = tmpfs("run", "size=2m") / "paper"
    subprocess.run(["cp", "-a", str(paper_run), str(copy)], check=True)
    subprocess.run(["mount", "-o", "remount,ro", str(copy.parent)], check=True)
    assert main(["plot", str(copy)]) == 2
    assert "cannot write there (Read-only file system)" in capsys.readouterr().err
