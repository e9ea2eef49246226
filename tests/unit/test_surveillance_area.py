"""A configured surveillance target exists only while it is inside the area, as a born target
(which leaves there) and a track (which is deleted there): one that flew out was scored as a
missed target, and its deleted track as a break, every scan to the end of the run."""

from __future__ import annotations

import json

import numpy as np
import yaml
from test_surveillance_run import base

from covnet.cli.app import main
from covnet.covariance_control import surveillance
from covnet.covariance_control.config import from_dict


def _flying_out():
    d = base(scans=16)
    d["targets"][0] = {  # x = 17 km + 300 m/s: out of the 20 km area after about 10 scans
        "id": "E",
        "initial_position_m": [17000.0, 8000.0],
        "initial_velocity_mps": [300.0, 0.0],
    }
    return d


def test_a_configured_target_leaves_where_it_leaves_the_area():
    sm = surveillance.build(from_dict(_flying_out()))
    ex, x = sm.exists[0], sm.truth[0][:, 0]  # E is the first configured target
    inside = ~np.isnan(x)
    assert np.array_equal(ex, inside)
    first_out = int(np.flatnonzero(~ex)[0])
    assert 5 <= first_out <= 12 and not ex[first_out:].any()
    assert np.all(x[ex] <= 20000.0)
    # the others as before (inside all along)
    sm0 = surveillance.build(from_dict(base(scans=16)))
    assert np.array_equal(sm.exists[1:], sm0.exists[1:])


def test_no_missed_target_scored_once_it_has_left(tmp_path):
    cfg = tmp_path / "out.yaml"
    cfg.write_text(yaml.safe_dump(_flying_out()))
    out = tmp_path / "run"
    assert main(["run", str(cfg), "--out", str(out), "--no-figures"]) == 0
    sm = surveillance.build(from_dict(_flying_out()))
    with np.load(out / "arrays.npz") as a:
        m = json.loads((out / "summary.json").read_text())["metrics"]
        metric = next(iter(m))
        n_truth = a[f"n_truth.{metric}"]
    assert np.array_equal(n_truth, sm.exists.sum(axis=0))
    e_out = int(np.flatnonzero(~sm.exists[0])[0])  # E is the first configured target
    others = sm.exists[1:].sum(axis=0)
    assert np.array_equal(n_truth[e_out:], others[e_out:])  # E no longer counted
