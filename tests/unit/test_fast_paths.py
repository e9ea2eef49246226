"""The throughput shortcuts of ``covnet up`` change costs, never results: the recorder's
``peek`` reads what a strict decode reads, a sensor's noise table draws what
``covnet.covariance_control.model.measure`` draws, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.covariance_control.model import build_model, measure, truth_trajectory
from covnet.runs.recording import peek
from covnet.wire import messages as msg
from sensors.covariance import NoiseTable


def _paper_messages() -> list[msg.Message]:
    z = np.array([[1.5, -2.0]])
    return [
        msg.Command(scan=3, t=3.0, enabled=("S1",), t_sent_ns=11, episode=2),
        msg.Measurement(sensor_id="S1", scan=3, t=3.0, z=z, R=np.eye(2), t_sent_ns=12),
        msg.Truth(scan=4, t=4.0, target_ids=("T1",), states=np.ones((1, 4))),
        msg.Track(scan=3, t=3.0, x=np.ones(4), P=np.eye(4), t_sent_ns=13),
        msg.Heartbeat(role="sensor", node_id="S1", scan=3, t_sent_ns=14, rejected={"x": 1}),
    ]


@pytest.mark.parametrize("m", _paper_messages(), ids=lambda m: m.KIND)
def test_peek_reads_kind_stamp_and_scan(m):
    assert peek(msg.encode(m)) == (m.KIND, getattr(m, "t_sent_ns", None), m.scan)


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"", "not_msgpack"),
        (b"\xc1", "not_msgpack"),
        (b"\x93\x01\x02\x03", "not_a_map"),
        (b"\x81\xa1v\x02", "bad_version"),
        (b"\x82\xa1v\x01\xa1k\xa3zzz", "unknown_kind"),
    ],
)
def test_peek_names_what_is_undecodable(payload, reason):
    assert peek(payload) == (f"undecodable:{reason}", None, None)


def test_constructor_names_are_plain_str_even_when_cached():
    class Name(str):
        pass

    msg.Command(scan=1, t=1.0, enabled=("S1",), t_sent_ns=1)  # "S1" is now a known id
    cmd = msg.Command(scan=1, t=1.0, enabled=(Name("S1"),), t_sent_ns=1)
    assert type(cmd.enabled[0]) is str
    with pytest.raises(msg.WireError, match="bad_value"):
        msg.Command(scan=1, t=1.0, enabled=("S1", "S1"), t_sent_ns=1)


def test_noise_table_is_measure_bit_for_bit(paper):
    model = build_model(paper)
    truth = truth_trajectory(model)
    for j in range(len(model.sensor_ids)):
        noisy = NoiseTable(model, j)
        assert len(noisy.table) == model.scans
        for k in range(1, model.scans + 2):  # the last one is past the table: drawn
            x = truth[min(k, model.scans) - 1]
            assert noisy(k, x).tobytes() == measure(model, j, k, x).tobytes()


def test_manager_fuses_with_gains_computed_ahead_bit_for_bit(paper):
    from covnet.covariance_control.centre import Gains, fuse_with_gains
    from covnet.covariance_control.model import (
        fuse,
        fused_covariance,
        initial_estimate,
        predict_step,
    )

    model = build_model(paper)
    ids = model.sensor_ids
    rng = np.random.default_rng(7)
    est = initial_estimate(model, "perturbed")
    for k in range(1, 30):
        pred = predict_step(model, est)
        subset = tuple(sorted(rng.choice(len(ids), size=int(rng.integers(0, 6)), replace=False)))
        gains = Gains.of(model, pred.P, subset)
        expected_P = fused_covariance(model, pred.P, [(j, model.R[j]) for j in subset])
        assert gains.P_post.tobytes() == expected_P.tobytes()
        got = {
            ids[j]: msg.Measurement(
                sensor_id=ids[j],
                scan=k,
                t=1.0,
                z=rng.normal(size=(1, 2)),
                R=model.R[j],
                t_sent_ns=1,
            )
            for j in reversed(subset)  # arrival order does not matter
        }
        est = fuse(model, pred, [(ids.index(s), m.z[0], m.R) for s, m in got.items()])
        fast = fuse_with_gains(gains, model, pred, got, ids)
        assert fast is not None
        assert fast.x.tobytes() == est.x.tobytes() and fast.P.tobytes() == est.P.tobytes()
        if subset:  # one missing, or another R: not the gains it needs
            assert fuse_with_gains(gains, model, pred, dict(list(got.items())[1:]), ids) is None
            first = ids[subset[0]]
            other = {
                **got,
                first: msg.Measurement(
                    sensor_id=first,
                    scan=k,
                    t=1.0,
                    z=[[0.0, 0.0]],
                    R=2 * model.R[subset[0]],
                    t_sent_ns=1,
                ),
            }
            assert fuse_with_gains(gains, model, pred, other, ids) is None


def test_a_short_noise_table_draws_the_scans_past_it(paper):
    """A table of the first scans only (a sensor process's start-up budget): every scan is
    still ``measure``'s bits, from the table or drawn."""
    model = build_model(paper)
    truth = truth_trajectory(model)
    for ahead in (0, 1, 37):
        noisy = NoiseTable(model, 3, ahead)
        assert sorted(noisy.table) == list(range(1, ahead + 1))
        for k in range(1, model.scans + 1):
            assert noisy(k, truth[k - 1]).tobytes() == measure(model, 3, k, truth[k - 1]).tobytes()


def test_a_sensor_process_reserves_its_start_up_draws(monkeypatch):
    """At most ``MAX_SCANS`` a sensor and ``PROCESS_DRAWS`` a process, first come first served:
    the 64 hosted sensors of a 20 000-scan run no longer draw 1.28 million noises at start."""
    monkeypatch.setattr(NoiseTable, "_reserved", 0)
    assert NoiseTable.MAX_SCANS == 20_000 and NoiseTable.PROCESS_DRAWS == 400_000
    assert NoiseTable.reserve(100) == 100
    assert NoiseTable.reserve(50_000) == 20_000
    monkeypatch.setattr(NoiseTable, "_reserved", 0)
    got = [NoiseTable.reserve(20_000) for _ in range(64)]  # 64 hosted sensors, a long run
    assert got == [20_000] * 20 + [0] * 44 and sum(got) == NoiseTable.PROCESS_DRAWS
    monkeypatch.setattr(NoiseTable, "_reserved", 0)
    got = [NoiseTable.reserve(6_000) for _ in range(70)]
    assert got[:66] == [6_000] * 66 and got[66:] == [4_000, 0, 0, 0]
