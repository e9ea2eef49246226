"""A run directory whose ``arrays.npz`` is damaged (emptied, cut short, a flipped byte, or
another file in its place) is named with what is wrong, exit 2, by ``covnet plot`` and
``covnet export``; they ended in a ``BadZipFile`` or ``EOFError`` traceback."""

from __future__ import annotations

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
