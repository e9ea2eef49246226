"""Commands that read a run directory never write over it (a hunt through damaged and
misused run directories found both):

- ``covnet replay RUN --out RUN --force`` emptied the run it was asked to read (recording,
  summary, arrays), then failed on the missing config; ``--out`` may now be neither the run
  nor a folder holding it, and the default ``RUN/replay`` that is a file is named;
- ``covnet export RUN --out RUN/summary.json`` wrote CSV over the run's summary (exit 0); an
  existing ``--out`` is now replaced only with ``--force``, and a run's own file never."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from covnet.cli.app import main
from covnet.errors import UsageError
from covnet.runs.rundir import prepare_out
from tests.conftest import REPO


def _digest(d: Path) -> dict[str, str]:
    return {
        str(p.relative_to(d)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(d.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("r") / "run"
    assert main(["run", str(REPO / "configs" / "paper.yaml"), "--no-figures", "--out", str(d)]) == 0
    (d / "recording.mcap").write_bytes(b"")  # with run.json, what a replay checks for first
    return d


def test_prepare_out_refuses_the_directory_read_or_one_holding_it(tmp_path):
    src = tmp_path / "a" / "run"
    src.mkdir(parents=True)
    for out in (src, tmp_path / "a", tmp_path / "a" / "." / "run"):
        with pytest.raises(UsageError, match="the directory this command reads"):
            prepare_out(out, "replay", True, reads=src)
    assert prepare_out(src / "sub", "replay", True, reads=src) == src / "sub"


@pytest.mark.parametrize("out", [".", ".."])
def test_replay_out_the_run_itself_with_force_deletes_nothing(run_dir, out, capsys):
    before = _digest(run_dir)
    assert main(["replay", str(run_dir), "--out", str(run_dir / out), "--force"]) == 2
    assert "the directory this command reads" in capsys.readouterr().err
    assert _digest(run_dir) == before


def test_replay_default_out_that_is_a_file_is_named(tmp_path, run_dir, capsys):
    import shutil

    d = tmp_path / "copy"
    shutil.copytree(run_dir, d)
    (d / "replay").write_text("mine")
    assert main(["replay", str(d)]) == 2
    assert "exists and is not a directory" in capsys.readouterr().err
    assert (d / "replay").read_text() == "mine"


@pytest.mark.parametrize("name", ["summary.json", "arrays.npz", "config.json"])
def test_export_never_writes_over_the_runs_own_files(run_dir, name, capsys):
    before = _digest(run_dir)
    for extra in ([], ["--force"]):
        assert main(["export", str(run_dir), "--out", str(run_dir / name), *extra]) == 2
        assert "one of the run's own files" in capsys.readouterr().err
    assert _digest(run_dir) == before


def test_export_replaces_an_existing_file_only_with_force(tmp_path, run_dir, capsys):
    out = tmp_path / "mine.csv"
    out.write_text("keep me")
    assert main(["export", str(run_dir), "--out", str(out)]) == 2
    assert "exists; choose another name or pass --force" in capsys.readouterr().err
    assert out.read_text() == "keep me"
    assert main(["export", str(run_dir), "--out", str(out), "--force"]) == 0
    assert out.read_text().startswith("kind,episode,id,scan")
    # the default name in the run directory is the export's own: replaced without a word
    assert main(["export", str(run_dir)]) == 0 and main(["export", str(run_dir)]) == 0


@pytest.mark.parametrize("fmt", ["csv", "stonesoup"])
def test_export_force_replaces_its_own_earlier_export_in_the_run(tmp_path, run_dir, capsys, fmt):
    """An export under a name of one's own in the run directory could not be replaced: with
    ``--force`` it was "one of the run's own files".  The run's files still never are."""
    if fmt == "stonesoup":
        pytest.importorskip("stonesoup")
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    argv = ["export", str(run), "--format", fmt, "--out", str(run / f"mine.{fmt}")]
    assert main(argv) == 0
    assert main([*argv, "--force"]) == 0, capsys.readouterr().err
    assert main(["export", str(run), "--out", str(run / "summary.json"), "--force"]) == 2
    assert "is one of the run's own files" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("content", "says"),
    [(b"[]", "not a JSON object"), (b"42", "not a JSON object"), (b"", "cannot read")],
)
def test_replay_of_a_run_whose_run_json_is_damaged_is_a_usage_error(
    tmp_path, run_dir, capsys, content, says
):
    """``run.json`` a list, a number (an AttributeError traceback) or empty (exit 1, where a
    missing one is exit 2): every file of the run that cannot be read is the user's input."""
    import shutil

    d = tmp_path / "copy"
    shutil.copytree(run_dir, d)
    (d / "run.json").write_bytes(content)
    assert main(["replay", str(d)]) == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err


def _small(tmp_path: Path, name: str, scans: int = 3) -> Path:
    text = (REPO / "configs" / "paper.yaml").read_text()
    cfg = tmp_path / name
    cfg.write_text(text.replace("scans: 100", f"scans: {scans}", 1))
    assert f"scans: {scans}" in cfg.read_text()
    return cfg


@pytest.mark.parametrize("cmd", [["run", "--no-figures"], ["mc", "--trials", "1", "--no-figures"]])
def test_force_never_empties_the_directory_holding_the_config(tmp_path, capsys, cmd):
    """``covnet run OUT/my.yaml --out OUT --force`` (OUT an earlier run) deleted the user's
    ``my.yaml`` with the rest of OUT, and exited 0; the batch commands alike.  Now refused,
    naming the file, and OUT untouched."""
    out = tmp_path / "out"
    first = _small(tmp_path, "first.yaml")
    assert main([cmd[0], str(first), *cmd[1:], "--out", str(out), "--metric", "kl"]) == 0
    mine = out / "my.yaml"
    mine.write_text(first.read_text())
    before = _digest(out)
    capsys.readouterr()
    assert main([cmd[0], str(mine), *cmd[1:], "--out", str(out), "--force", "--metric", "kl"]) == 2
    err = capsys.readouterr().err
    assert f"it holds {mine.resolve()}, which this command reads" in err, err
    assert _digest(out) == before
    # elsewhere, --force works as before
    other = tmp_path / "other"
    assert main([cmd[0], str(mine), *cmd[1:], "--out", str(other), "--metric", "kl"]) == 0
    assert (
        main([cmd[0], str(mine), *cmd[1:], "--out", str(other), "--force", "--metric", "kl"]) == 0
    )
