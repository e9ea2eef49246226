"""Issue 26: a password holder may impersonate its sensor, but the manager must not fuse a
measurement kilometres from its prediction.  S3's process here sends well-formed measurements
moved 20 km east on its own key (what a forger holding S3's password did): the validation gate
(:mod:`covnet.core.validation_gate`) rejects every one of them, counted as ``outside_gate``
under S3's key, the track stays on the target, and ``covnet replay`` of the run reproduces it
byte for byte (the replay applies the same gate to the recorded messages)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from nodethreads import Forger, run_recorded_network

from covnet.core.validation_gate import TAIL, passes_measurement, threshold
from covnet.covariance_control.config import with_overrides
from covnet.covariance_control.model import build_model, truth_trajectory
from covnet.covariance_control.replay import replay_run
from covnet.wire import messages as msg

SHIFT = np.array([20_000.0, 0.0])


def _shifted(m):
    """S3's measurement moved by :data:`SHIFT`."""
    return dataclasses.replace(m, z=m.z + SHIFT)


def test_the_gate_is_chi_square_with_a_billionth_tail():
    # two degrees of freedom: P(χ² > x) = exp(-x/2)
    assert threshold(2) == pytest.approx(-2 * np.log(TAIL), rel=1e-12)
    # four: exp(-x/2)(1 + x/2)
    g = threshold(4)
    assert np.exp(-g / 2) * (1 + g / 2) == pytest.approx(TAIL, rel=1e-9)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    P, R, x = np.eye(4), np.eye(2), np.zeros(4)
    # S = P_pos + R = 2 I, so d² = |ν|² / 2 and the edge is |ν| = sqrt(2 γ) = 9.105...
    edge = np.sqrt(2 * threshold(2))
    assert passes_measurement(np.array([edge - 1e-6, 0.0]), R, H, x, P)
    assert not passes_measurement(np.array([0.0, edge + 1e-6]), R, H, x, P)


def test_a_forged_sensor_is_never_fused_and_the_replay_agrees(paper, tmp_path):
    # the manager waits for S3's genuine answer until the scan's timeout: keep it short
    net = paper.network.model_dump() | {"record": True, "scan_timeout_s": 0.2}
    sc = with_overrides(paper, scans=20, network=net)
    out = tmp_path / "run"
    forger = {"S3": lambda bus: Forger(bus, _shifted)}
    result, _ = run_recorded_network(sc, ["spectral"], out, wrap_bus=forger)
    assert result.completed and result.error is None
    log = result.episodes["spectral"].as_run(len(sc.sensor_ids))
    s3 = sc.sensor_ids.index("S3")
    asked = int(log.enabled[:, s3].sum())
    assert asked > 0  # S3 was enabled, and every answer it sent was rejected
    rejected = result.stats.rejected_by_key[msg.measurement_key("t", "S3")]
    assert rejected["outside_gate"] == asked
    truth = truth_trajectory(build_model(sc))
    err = np.hypot(log.x_est[:, 0] - truth[:, 0], log.x_est[:, 2] - truth[:, 2])
    assert err.max() < 100.0  # metres: on the target, not 20 km away
    report = replay_run(out)
    assert report.identical, report.differences


class StatusForger(Forger):
    """A node's bus that, with each measurement it sends, also publishes a forged Status of that
    scan on the manager's status key (a password holder impersonating the manager)."""

    def __init__(self, bus):
        super().__init__(bus, lambda m: m)

    def publish(self, key, payload):
        self.bus.publish(key, payload)
        try:
            msg.parse_measurement_key(key)
        except ValueError:
            return None
        m = msg.decode_as(payload, msg.Measurement)
        forged = msg.Status(
            scan=m.scan, t=m.t, enabled=(), trace_P=0.0, trace_Pd=0.0, value=0.0,
            t_sent_ns=m.t_sent_ns, episode=m.episode,
        )  # fmt: skip
        return self.bus.publish(msg.status_key("t"), msg.encode(forged))


def test_forged_statuses_are_counted(paper, tmp_path):
    """Issue 26: forged manager Status messages were counted nowhere.  The recorder hears every
    Status and counts a second one of a key, episode and scan (``repeated_status``), which the
    manager's network.json reports under the recorder."""
    net = paper.network.model_dump() | {"record": True, "heartbeat_s": 0.05}
    sc = with_overrides(paper, scans=15, network=net)
    result, _ = run_recorded_network(
        sc, ["spectral"], tmp_path / "run", wrap_bus={"S5": StatusForger}
    )
    assert result.completed
    assert result.stats.node_rejected.get("recorder", {}).get("repeated_status", 0) > 0
