"""``configs/large_multitarget.yaml`` (issue 29): 64 sensors on 8 targets, decided by the bounded
assignment search; ``covnet run`` and ``covnet up`` in lockstep give the same results, the
per-scan value, certified lower bound and gap included, and the live view shows the gap."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from multiproc import assert_nothing_left, assert_status_shows_gap, up_lockstep

from covnet.cli.app import main as covnet_main
from covnet.runs.rundir import load_arrays

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

LARGE_MT = Path(__file__).resolve().parents[2] / "configs" / "large_multitarget.yaml"


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "run"
    assert covnet_main(["run", str(LARGE_MT), "--out", str(out), "--no-figures"]) == 0
    return out


@pytest.fixture(scope="module")
def lockstep_up(tmp_path_factory):
    out = tmp_path_factory.mktemp("up") / "run"
    return out, up_lockstep(LARGE_MT, out)


def test_large_multitarget_up_equals_run(reference, lockstep_up):
    out, _ = lockstep_up
    ref = json.loads((reference / "summary.json").read_text())
    got = json.loads((out / "summary.json").read_text())
    assert got["completed"] is True and len(got["sensor_ids"]) == 64
    assert got["metrics"] == ref["metrics"]  # assignments, values, lower bounds, gaps
    a_ref, a_got = load_arrays(reference / "arrays.npz"), load_arrays(out / "arrays.npz")
    for m in ref["metrics"]:
        for name in ("assignment", "x_est", "P_post", "value", "lower_bound", "gap"):
            assert np.array_equal(a_got[f"{name}.{m}"], a_ref[f"{name}.{m}"]), (m, name)
        blk = got["metrics"][m]
        assert len(blk["targets"]) == 8
        assert len(blk["gap"]) == 12 and all(0.0 <= g <= 1.0 for g in blk["gap"])
        assert all(lb <= v for lb, v in zip(blk["lower_bound"], blk["value"], strict=True))


def test_large_multitarget_up_lost_nothing_and_showed_the_gap(lockstep_up):
    out, output = lockstep_up
    net = json.loads((out / "network.json").read_text())
    assert net["rejected"] == {} and net["lost"] == 0
    assert_status_shows_gap(output)
    assert_nothing_left(out)
