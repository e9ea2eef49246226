"""The README recipe "Adding a sensor model", executed: a range-only sensor written in this file
as the recipe says (a :class:`~covnet.core.sensor_models.SensorModel` subclass with its config
fields, ``h``, ``H``, ``R``; one line in :data:`~covnet.core.sensor_models.SENSOR_MODELS`),
registered in the registry for this test only, is accepted by the config with its own keys and
runs through ``covnet run``, a lockstep network run (world, sensors, recorder and manager
threads over the in-memory bus: they see the temporary registry) equal to it bit for bit, and
``covnet replay`` of that network run.  The recipe is true while this test passes."""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
import yaml
from nodethreads import NodeThreads, with_metrics
from numpy.typing import ArrayLike

from covnet.cli.app import main as covnet_main
from covnet.clock import WallClock
from covnet.config import ConfigError
from covnet.core import sensor_models
from covnet.core.gaussian import Mat
from covnet.core.sensor_models import STATE_DIM, SensorModel, check_positive
from covnet.covariance_control.config import config_hash, from_dict, normalised
from covnet.covariance_control.replay import RECORDING
from covnet.covariance_control.results import write_network_run
from covnet.runs.recording import RecordingWriter, run_metadata
from covnet.runs.rundir import load_arrays
from manager import covariance as manager_node
from recorder import node as recorder_node
from sensors import covariance as sensor_node
from world import covariance as world_node

RUN = "t"
METRIC = "abs_trace"


# -- the new model: what the recipe asks for --------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class RangeFields:
    """``model: range``: ``R = [[σ²]]`` from ``sigma_m`` (m)."""

    sigma_m: float = field(metadata={"check": check_positive})


@dataclass(frozen=True, slots=True, kw_only=True)
class RangeModel(SensorModel):
    """Range only: ``h(x) = [r]``, ``H = [[dx/r, 0, dy/r, 0]]``, ``R = [[σ²]]``."""

    kind: ClassVar[str] = "range"
    dim_z: ClassVar[int] = 1
    angle_components: ClassVar[tuple[bool, ...]] = (False,)
    undefined_at_sensor: ClassVar[bool] = True  # H is undefined at r = 0
    config_fields: ClassVar[type[Any]] = RangeFields

    sigma_r: float

    @classmethod
    def from_fields(cls, fields: Any, **common: Any) -> SensorModel:
        return cls(sigma_r=fields.sigma_m, **common)

    def _noise(self) -> Mat:
        return np.array([[self.sigma_r * self.sigma_r]])

    def h(self, x: ArrayLike) -> Mat:
        return self.relative(x)[2][..., None]

    def jacobian(self, x: ArrayLike) -> Mat:
        dx, dy, r = self.relative(x)
        if np.any(r == 0.0):
            raise ValueError("x: the range Jacobian is undefined at the sensor's position")
        H = np.zeros(r.shape + (1, STATE_DIM))
        H[..., 0, 0] = dx / r
        H[..., 0, 2] = dy / r
        return H


@pytest.fixture()
def registry(monkeypatch):
    """The new model in the registry for this test only (``monkeypatch`` restores it)."""
    before = dict(sensor_models.SENSOR_MODELS)
    monkeypatch.setitem(sensor_models.SENSOR_MODELS, RangeModel.kind, RangeModel)
    yield sensor_models.SENSOR_MODELS
    monkeypatch.undo()
    assert sensor_models.SENSOR_MODELS == before


# -- a small scenario using it ----------------------------------------------------------------


def scenario(scans: int = 10) -> dict[str, Any]:
    """Two targets, two position sensors and three range sensors around a 10 km square, with
    misses and clutter (so that the range sensors' returns are gated and associated)."""

    def rng(i: str, xy: list[float]) -> dict[str, Any]:
        return {"id": i, "model": "range", "position_m": xy, "sigma_m": 5.0,
                "max_range_m": 20000.0, "pd": 0.9, "clutter_rate": 0.3}  # fmt: skip

    loose = [{"from_scan": 1, "diag": [400.0, 10.0, 400.0, 10.0]}]
    return {
        "name": "range_recipe",
        "seed": 7,
        "scans": scans,
        "targets": [
            {
                "id": "T1",
                "initial_position_m": [2000.0, 3000.0],
                "initial_velocity_mps": [120.0, 40.0],
                "desired": loose,
            },
            {
                "id": "T2",
                "initial_position_m": [8000.0, 7000.0],
                "initial_velocity_mps": [-20.0, -60.0],
                "desired": loose,
            },
        ],
        "sensors": [
            {
                "id": "P1",
                "position_m": [5000.0, 5000.0],
                "sigma_x_m": 40.0,
                "sigma_y_m": 15.0,
                "rho": 0.5,
                "max_range_m": 20000.0,
                "pd": 0.9,
                "clutter_rate": 0.3,
            },
            {
                "id": "P2",
                "position_m": [5000.0, 5000.0],
                "sigma_x_m": 15.0,
                "sigma_y_m": 40.0,
                "rho": -0.5,
                "max_range_m": 20000.0,
                "pd": 0.9,
                "clutter_rate": 0.3,
            },
            rng("G1", [0.0, 0.0]),
            rng("G2", [10000.0, 0.0]),
            rng("G3", [0.0, 10000.0]),
        ],
        "allocation": {"metrics": [METRIC], "max_active": 4},
        "ospa": {"cutoff_m": 500.0, "order": 2.0},
    }


def test_the_config_takes_the_new_model_with_its_own_keys(registry):
    sc = from_dict(scenario())
    g1 = sc.sensors[2]
    assert g1.model == "range" and g1.fields == RangeFields(sigma_m=5.0)
    data = normalised(sc)
    assert data["sensors"][2]["sigma_m"] == 5.0
    assert config_hash(from_dict(json.loads(json.dumps(data)))) == config_hash(sc)
    bad = scenario()
    bad["sensors"][2]["sigma_bearing_mrad"] = 1.0
    bad["sensors"][3].pop("sigma_m")
    bad["sensors"][0]["sigma_m"] = 3.0
    with pytest.raises(ConfigError) as info:
        from_dict(bad)
    got = dict(info.value.problems)
    assert got["sensors[2].sigma_bearing_mrad"] == (
        "not a field of model range (only for range_bearing, bearing sensors)"
    )
    assert got["sensors[3].sigma_m"] == "missing required key (a range sensor needs sigma_m)"
    assert got["sensors[0].sigma_m"] == "not a field of model position (only for range sensors)"
    bad = scenario()
    bad["sensors"][4]["sigma_m"] = -1.0  # the model's own check, with the structure
    with pytest.raises(ConfigError) as info:
        from_dict(bad)
    assert info.value.problems == [("sensors[4].sigma_m", "must be > 0, got -1.0")]


def test_without_the_entry_the_model_is_unknown():
    with pytest.raises(ConfigError) as info:
        from_dict(scenario())
    assert any(p == "sensors[2].model" and "'range'" in m for p, m in info.value.problems)


def _network_run(sc, out: Path):
    """World, sensors, recorder and manager as threads over one in-memory hub, in lockstep;
    the manager's run directory written as ``python -m manager`` writes it."""
    out.mkdir(parents=True)
    nodes = NodeThreads()
    writer = RecordingWriter(out / RECORDING, run_id=RUN, metadata=run_metadata(RUN, sc))
    try:
        nodes.start(
            "recorder", lambda b, ev: recorder_node.run(sc, b, RUN, WallClock(), ev, writer)
        )
        nodes.start("world", lambda b, ev: world_node.run(sc, b, RUN, WallClock(), ev))
        for sid in sc.sensor_ids:
            nodes.start(sid, lambda b, ev, s=sid: sensor_node.run(sc, s, b, RUN, WallClock(), ev))
        mbus = nodes.bus("manager")
        try:
            result = manager_node.run(
                with_metrics(sc, [METRIC]), mbus, RUN, WallClock(), threading.Event()
            )
        finally:
            mbus.close()
            nodes.close()
        assert not any(th.is_alive() for th in nodes.threads)
    finally:
        writer.close()
    write_network_run(out, sc, result, {"episodes": [METRIC], "run_id": RUN})
    return result


def test_recipe_runs_through_run_network_and_replay(registry, tmp_path, capsys):
    data = scenario()
    cfg = tmp_path / "range.yaml"
    cfg.write_text(yaml.safe_dump(data))

    # (a) covnet run
    ref = tmp_path / "ref"
    assert covnet_main(["run", str(cfg), "--out", str(ref), "--no-figures"]) == 0
    ra = load_arrays(ref / "arrays.npz")
    G = [2, 3, 4]  # the range sensors
    assignment = ra[f"assignment.{METRIC}"]
    assert (assignment[..., G] >= 0).any(), "no range sensor was ever allocated"
    assert np.isfinite(ra[f"x_est.{METRIC}"]).all()

    # (b) the lockstep network run, bit for bit
    sc = from_dict(data)
    out = tmp_path / "net"
    result = _network_run(sc, out)
    assert result.completed and result.error is None
    assert result.stats.rejected == {} and result.stats.lost == 0
    rb = load_arrays(out / "arrays.npz")
    for key in ("assignment", "x_est", "P_post", "returns", "ospa"):
        np.testing.assert_array_equal(ra[f"{key}.{METRIC}"], rb[f"{key}.{METRIC}"], err_msg=key)
    a = json.loads((ref / "summary.json").read_text())
    b = json.loads((out / "summary.json").read_text())
    assert a["metrics"] == b["metrics"]

    # (c) covnet replay of the network run
    capsys.readouterr()
    assert covnet_main(["replay", str(out)]) == 0
    assert "identical" in capsys.readouterr().out
    assert (out / "replay" / "summary.json").read_bytes() == (out / "summary.json").read_bytes()


def test_the_range_model_is_consistent(registry):
    """h and H of the new model agree (central differences), and its information is
    ``p HᵀR⁻¹H``."""
    m = RangeModel(sensor_xy=(100.0, -50.0), sigma_r=5.0, pd=0.8)
    x = np.array([3100.0, 10.0, 3950.0, -4.0])
    eps = 1e-3
    fd = [(m.h(x + eps * e) - m.h(x - eps * e))[0] / (2 * eps) for e in np.eye(4)]
    np.testing.assert_allclose(m.jacobian(x)[0], fd, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(m.h(x), [math.hypot(3000.0, 4000.0)])
    H = m.jacobian(x)
    np.testing.assert_allclose(
        sensor_models.predicted_information(m, x), 0.8 * H.T @ H / 25.0, rtol=1e-12
    )
