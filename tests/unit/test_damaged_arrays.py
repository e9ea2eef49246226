"""A run directory whose ``arrays.npz`` is damaged (emptied, cut short, a flipped byte, or
another file in its place) is named with what is wrong, exit 2, by ``covnet plot`` and
``covnet export``; they ended in a ``BadZipFile`` or ``EOFError`` traceback."""

from __future__ import annotations

import json
import shutil

import pytest
import yaml

from covnet.cli.app import main
from covnet.errors import UsageError
from covnet.runs.rundir import load_arrays


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, paper_path):
    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = 5
    root = tmp_path_factory.mktemp("dmg")
    cfg = root / "p5.yaml"
    cfg.write_text(yaml.safe_dump(data))
    out = root / "run"
    assert main(["run", str(cfg), "--out", str(out), "--metric", "spectral", "--no-figures"]) == 0
    return out


def _damaged(raw: bytes, how: str) -> bytes:
    mid = len(raw) // 2
    return {
        "emptied": b"",
        "cut short": raw[:mid],
        "a flipped byte": raw[:mid] + bytes([raw[mid] ^ 0xFF]) + raw[mid + 1 :],
        "another file": b"hello, not an archive\n",
    }[how]


@pytest.mark.parametrize("how", ["emptied", "cut short", "a flipped byte", "another file"])
def test_a_damaged_arrays_file_is_named(run_dir, tmp_path, capsys, how):
    bad = tmp_path / "run"
    shutil.copytree(run_dir, bad)
    raw = (run_dir / "arrays.npz").read_bytes()
    assert load_arrays(run_dir / "arrays.npz")  # the original reads
    (bad / "arrays.npz").write_bytes(_damaged(raw, how))
    with pytest.raises(UsageError, match="arrays.npz: not a readable arrays file"):
        load_arrays(bad / "arrays.npz")
    capsys.readouterr()
    for cmd in (["plot", str(bad)], ["export", str(bad)]):
        assert main(cmd) == 2, cmd
        err = capsys.readouterr().err
        assert f"{bad / 'arrays.npz'}: not a readable arrays file" in err and "Traceback" not in err
        if how == "another file":
            assert "not an .npz archive" in err and "unsafely" not in err


@pytest.fixture(scope="module")
def other_run(tmp_path_factory, run_dir):
    """The same config as :func:`run_dir` with another seed: a whole, readable ``arrays.npz``
    of the same shapes and names, with other numbers."""
    out = tmp_path_factory.mktemp("other") / "run"
    cfg = run_dir.parent / "p5.yaml"
    argv = ["run", str(cfg), "--out", str(out), "--metric", "spectral", "--seed", "7"]
    assert main([*argv, "--no-figures"]) == 0
    return out


def test_another_runs_arrays_file_is_named(run_dir, other_run, tmp_path, capsys):
    """Another run's ``arrays.npz`` copied into a run directory was drawn and exported as this
    run's (its numbers under this run's config and summary), exit 0.  The run's ``run.json``
    keeps the SHA-256 of the file it wrote; another file is named, exit 2."""
    bad = tmp_path / "run"
    shutil.copytree(run_dir, bad)
    shutil.copy(other_run / "arrays.npz", bad / "arrays.npz")
    assert load_arrays(other_run / "arrays.npz")  # a whole file, in its own run
    with pytest.raises(UsageError, match="arrays.npz: not the file this run wrote"):
        load_arrays(bad / "arrays.npz")
    capsys.readouterr()
    for cmd in (["plot", str(bad)], ["export", str(bad), "--out", str(tmp_path / "x.csv")]):
        assert main(cmd) == 2, cmd
        err = capsys.readouterr().err
        assert f"{bad / 'arrays.npz'}: not the file this run wrote" in err, err
        assert "Traceback" not in err
    assert not (tmp_path / "x.csv").exists()


def test_a_run_without_digests_reads_as_before(run_dir, other_run, tmp_path):
    """Runs written before the digests (no ``file_sha256`` in ``run.json``) read as before."""
    old = tmp_path / "run"
    shutil.copytree(run_dir, old)
    info = json.loads((old / "run.json").read_text())
    assert set(info["file_sha256"]) == {"arrays.npz"}
    del info["file_sha256"]
    (old / "run.json").write_text(json.dumps(info))
    shutil.copy(other_run / "arrays.npz", old / "arrays.npz")
    assert load_arrays(old / "arrays.npz")
    assert main(["export", str(old), "--out", str(tmp_path / "x.csv")]) == 0


def test_a_run_json_cut_short_is_named_not_skipped(run_dir, other_run, tmp_path, capsys):
    """A ``run.json`` cut short made ``plot`` and ``export`` skip the digest check silently
    (exit 0, another run's arrays drawn as this run's: hunt 14); it is named, exit 2."""
    bad = tmp_path / "run"
    shutil.copytree(run_dir, bad)
    raw = (bad / "run.json").read_bytes()
    (bad / "run.json").write_bytes(raw[: len(raw) // 2])
    shutil.copy(other_run / "arrays.npz", bad / "arrays.npz")
    capsys.readouterr()
    for cmd in (["plot", str(bad)], ["export", str(bad), "--out", str(tmp_path / "x.csv")]):
        assert main(cmd) == 2, cmd
        err = capsys.readouterr().err
        assert f"{bad / 'run.json'} cannot be read (" in err and "Traceback" not in err, err
        assert "arrays.npz cannot be checked against the digest it keeps" in err
