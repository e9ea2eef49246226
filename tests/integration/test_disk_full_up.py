"""``covnet up`` on a small tmpfs (root only): the disk fills while the manager writes its
results (700 kB), or already while the recorder records (300 kB).  Every node that cannot
write says so in one line naming its file (a manager or recorder traceback before), the
launcher's error names the file too, ``run.json`` says ``failed`` (or the message says it
could not), and neither ``live.json`` nor a temporary file stays."""

from __future__ import annotations

import json
import re

import pytest
from multiproc import CovnetProcess, assert_nothing_left

from tests.conftest import PAPER

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(240)]

FULL = "No space left on device"


@pytest.mark.parametrize("size", ["700k", "300k"])
def test_up_on_a_full_disk_names_the_file_and_ends_failed(tmpfs, size):
    out = tmpfs("small", f"size={size}") / "up"
    p = CovnetProcess(["up", str(PAPER), "--out", str(out), "--no-figures"])
    try:
        rc = p.wait(timeout=150)
    finally:
        p.stop()
    text = p.output()
    assert rc == 1, text
    assert "Traceback" not in text, text
    nodes = [ln for ln in text.splitlines() if re.match(r"\[\w+\] \w+: error:", ln)]
    assert nodes, text  # the manager (and at 300 kB the recorder) could not write
    for ln in nodes:
        assert re.search(rf"error: {re.escape(str(out))}/\S+: {FULL}$", ln), ln
    (final,) = [ln for ln in text.splitlines() if ln.startswith("covnet: error:")]
    assert f"{out}/" in final and FULL in final, final
    if "run.json does not say" not in final:
        assert json.loads((out / "run.json").read_text())["status"] == "failed"
    left = sorted(p.name for p in out.iterdir() if p.name == "live.json" or ".tmp" in p.name)
    assert left == [], left
    assert_nothing_left(out)


def test_a_full_tmpdir_is_named_in_run_json(tmpfs, tmp_path, monkeypatch):
    """A long run whose per-scan rows spill into a full ``$TMPDIR`` (the run directory's disk
    has room): the manager's line names the folder, and so does ``run.json``'s ``ended``,
    which said only "the manager exited with status 1"."""
    import yaml

    tmp = tmpfs("tmp", "size=8k")
    data = yaml.safe_load(PAPER.read_text())
    data["scans"] = 1100  # past one block of rows (covnet.runs.columns.BLOCK): a spill file
    cfg = tmp_path / "long.yaml"
    cfg.write_text(yaml.safe_dump(data))
    out = tmp_path / "up"
    monkeypatch.setenv("TMPDIR", str(tmp))
    p = CovnetProcess(["up", str(cfg), "--out", str(out), "--no-figures", "--metric", "spectral"])
    try:
        rc = p.wait(timeout=150)
    finally:
        p.stop()
    text = p.output()
    assert rc == 1 and "Traceback" not in text, text
    assert re.search(rf"manager: error: .*{re.escape(str(tmp))}.*{FULL}", text), text
    ended = json.loads((out / "run.json").read_text())["ended"]
    assert str(tmp) in ended and "spill file" in ended and FULL in ended, ended
