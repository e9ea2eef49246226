"""An ``--out`` covnet cannot write to is named before the command runs (exit 2): a read-only
file system, ``/proc`` or a path through a file ran the whole scenario (about 7 s for
``configs/multitarget.yaml``), then failed on a temporary file, exit 1, without naming
``--out``."""

from __future__ import annotations

import time

import pytest

from covnet.cli.app import main
from tests.conftest import REPO


@pytest.mark.parametrize("where", ["proc", "through a file"])
@pytest.mark.parametrize("cmd", [["run"], ["mc", "--trials", "2"], ["up"]])
def test_an_unwritable_out_is_named_before_anything_runs(tmp_path, capsys, where, cmd):
    if where == "proc":
        out = "/proc/covnet-no-such-dir/run"
    else:
        (tmp_path / "a-file").write_text("x")
        out = str(tmp_path / "a-file" / "run")
    t0 = time.monotonic()
    argv = [cmd[0], str(REPO / "configs" / "multitarget.yaml"), *cmd[1:], "--out", out]
    assert main([*argv, "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert f"--out {out}: cannot write there" in err, err
    assert "Traceback" not in err
    assert time.monotonic() - t0 < 5.0  # nothing ran
