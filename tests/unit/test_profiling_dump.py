"""The stage profile (``COVNET_STAGES``): what a process writes, and a write that fails (a full
disk) names its file; ``covnet: error: No space left on device`` named none."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import pytest

from covnet.wire import profiling


def test_a_dump_writes_each_stage_in_the_directory_named(tmp_path, monkeypatch):
    monkeypatch.setenv(profiling.STAGES_ENV, str(tmp_path))
    st = profiling.Stages()
    st.lap("decide")
    st.lap("fuse")
    st.lap("fuse")
    st.dump("manager", scans=3)
    (f,) = tmp_path.glob("manager-*.json")
    doc = json.loads(f.read_text())
    assert doc["name"] == "manager" and doc["scans"] == 3
    assert doc["n"] == {"decide": 1, "fuse": 2} and set(doc["wall_ns"]) == {"decide", "fuse"}


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full")
def test_a_dump_on_a_full_disk_names_its_file(tmp_path, monkeypatch):
    monkeypatch.setenv(profiling.STAGES_ENV, str(tmp_path))
    monkeypatch.setattr(profiling, "_file", lambda where, name, suffix: Path("/dev/full"))
    st = profiling.Stages()
    st.lap("decide")
    with pytest.raises(OSError) as exc:
        st.dump("manager")
    assert exc.value.errno == errno.ENOSPC and exc.value.filename == "/dev/full"
