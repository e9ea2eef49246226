"""Required sensors with many targets: a required sensor is required while it can be on.  A
scan whose required sensors could not all be on at once (two of them covering only the same
target under ``max_per_target: 1``) turned every sensor off without a word; now the largest set
that fits stays required (:func:`covnet.covariance_control.targets.assignable`), the others are
free that scan, and the summary says how often each required sensor was off."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.cli.app import main
from covnet.covariance_control.targets import assignable

ROOT = Path(__file__).resolve().parents[2]


def _fits(sensors: tuple[int, ...], feas: np.ndarray, cap: int | None) -> bool:
    """Brute force: every sensor on a target it covers, at most ``cap`` a target."""
    choices = [np.flatnonzero(feas[j]).tolist() for j in sensors]
    if cap is None:
        return all(choices)
    for pick in itertools.product(*choices):
        if all(pick.count(t) <= cap for t in set(pick)):
            return True
    return False


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 6),
    t=st.integers(1, 3),
    cap=st.one_of(st.none(), st.integers(1, 2)),
    data=st.data(),
)
def test_assignable_is_a_largest_set_that_fits(n, t, cap, data):
    feas = np.array(
        data.draw(st.lists(st.lists(st.booleans(), min_size=t, max_size=t), min_size=n, max_size=n))
    )
    required = frozenset(data.draw(st.sets(st.integers(0, n - 1))))
    got = assignable(required, feas, cap)
    assert got <= required and _fits(tuple(sorted(got)), feas, cap)
    subsets = (
        c for r in range(len(required) + 1) for c in itertools.combinations(sorted(required), r)
    )
    best = max((len(c) for c in subsets if _fits(c, feas, cap)), default=0)
    assert len(got) == best


def test_assignable_keeps_the_lower_index_of_two_that_share_one_target():
    feas = np.array([[True, False], [True, False], [False, True]])
    assert assignable(frozenset({0, 1, 2}), feas, 1) == {0, 2}
    assert assignable(frozenset({0, 1, 2}), feas, 2) == {0, 1, 2}
    assert assignable(frozenset({0, 1, 2}), feas, None) == {0, 1, 2}
    # a holder moved to make room: 0 covers both, 1 only the first
    assert assignable(frozenset({0, 1}), np.array([[True, True], [True, False]]), 1) == {0, 1}


@pytest.fixture(scope="module")
def crowded(tmp_path_factory) -> Path:
    """configs/multitarget.yaml, 6 scans, two targets; P1 and P2 required, both near T1 and
    out of T2's reach, at most one sensor a target."""
    data = yaml.safe_load((ROOT / "configs" / "multitarget.yaml").read_text())
    data.update(scans=6)
    data["allocation"].update(metrics=["spectral"], required=["P1", "P2"], max_per_target=1)
    data["targets"] = data["targets"][:2]
    data["targets"][1]["initial_position_m"] = [19000.0, 19000.0]
    data["sensors"] = [s for s in data["sensors"] if s["id"] != "P3"]  # it would reach neither
    for s in data["sensors"]:
        if s["id"] == "P2":
            s["position_m"] = [3000.0, 1000.0]
    p = tmp_path_factory.mktemp("cfg") / "crowded.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_required_sensors_that_cannot_all_be_on_leave_the_others_allocated(
    crowded, tmp_path, capsys
):
    out = tmp_path / "run"
    assert main(["run", str(crowded), "--out", str(out), "--no-figures"]) == 0
    blk = json.loads((out / "summary.json").read_text())["metrics"]["spectral"]
    # every scan: P1 on T1 (required, fits), P2 free and off (no room), a sensor on T2
    assert blk["sensors_per_scan"] == [2] * 6
    assert all(a["P1"] == "T1" and "P2" not in a for a in blk["assignments"])
    assert all("T2" in a.values() for a in blk["assignments"])
    assert blk["required_off"] == {"P1": 0, "P2": 6}
    printed = capsys.readouterr().out
    assert "required sensors off: P2 in 6 of 6 scans" in printed
