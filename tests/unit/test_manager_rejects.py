"""The manager's acceptance test for measurements: every semantic fault counted by reason."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.clock import SimClock
from covnet.covariance_control.centre import usable_position, usable_track
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, Sample
from manager.loop import Loop as _Loop

RUN = "r1"


@pytest.fixture()
def loop(paper):
    return _Loop(paper.network, paper.sensor_ids, InMemoryBus(), RUN, SimClock())


def _sample(sensor_key: str, **fields) -> Sample:
    m = msg.Measurement(
        **(
            {
                "sensor_id": "S1",
                "scan": 5,
                "t": 5.0,
                "z": np.zeros((1, 2)),
                "R": np.eye(2),
                "t_sent_ns": 1,
                "episode": 0,
                "seq": 1,
            }
            | fields
        )
    )
    return Sample(msg.measurement_key(RUN, sensor_key), msg.encode(m), 2)


CASES = [
    ("accepted", _sample("S1"), None),
    ("key-mismatch", _sample("S2"), "key_mismatch"),
    ("late", _sample("S1", scan=4), "late"),
    ("future-scan", _sample("S1", scan=9), "wrong_scan"),
    ("earlier-episode", _sample("S1", episode=0, scan=99), "wrong_scan"),
    ("not-enabled", _sample("S3", sensor_id="S3"), "not_enabled"),
    ("two-detections", _sample("S1", z=np.zeros((2, 2))), "bad_measurement"),
    ("not-spd", _sample("S1", R=np.array([[1.0, 2.0], [2.0, 1.0]])), "bad_measurement"),
    ("unnumbered", _sample("S1", seq=None), "missing_seq"),  # every sensor numbers its own
]


@pytest.mark.parametrize("sample, reason", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_measurement_verdicts(loop, sample, reason):
    got: dict = {}
    waiting = {"S1", "S2"}
    loop._take(sample, 0, 5, waiting, got, usable_position)
    if reason is None:
        assert set(got) == {"S1"} and "S1" not in waiting and not loop.stats.rejected
    else:
        assert got == {} and dict(loop.stats.rejected) == {reason: 1}


def test_duplicate_is_rejected(loop):
    got: dict = {}
    waiting = {"S1"}
    loop._take(_sample("S1"), 0, 5, waiting, got, usable_position)
    loop._take(_sample("S1"), 0, 5, waiting, got, usable_position)
    assert set(got) == {"S1"} and dict(loop.stats.rejected) == {"duplicate": 1}


def test_garbage_counted_not_raised(loop):
    loop._take(
        Sample(msg.measurement_key(RUN, "S1"), b"\x00\x01", 1), 0, 5, {"S1"}, {}, usable_position
    )
    assert sum(loop.stats.rejected.values()) == 1


# decentralized modes: the sensors' keys carry local tracks


def _track_sample(sensor_key: str, **fields) -> Sample:
    m = msg.LocalTrack(
        **(
            {
                "sensor_id": "S1",
                "scan": 5,
                "t": 5.0,
                "x": np.zeros(4),
                "P": np.eye(4),
                "x_prior": np.zeros(4),
                "P_prior": 2.0 * np.eye(4),
                "t_sent_ns": 1,
                "episode": 0,
                "seq": 1,
            }
            | fields
        )
    )
    return Sample(msg.measurement_key(RUN, sensor_key), msg.encode(m), 2)


TRACK_CASES = [
    ("accepted", _track_sample("S1"), None),
    ("key-mismatch", _track_sample("S2"), "key_mismatch"),
    ("late", _track_sample("S1", scan=4), "late"),
    (
        "three-states",
        _track_sample("S1", x=np.zeros(3), P=np.eye(3), x_prior=np.zeros(3), P_prior=np.eye(3)),
        "bad_measurement",
    ),
    ("not-spd", _track_sample("S1", P=-np.eye(4)), "bad_measurement"),
    ("prior-not-spd", _track_sample("S1", P_prior=np.zeros((4, 4))), "bad_measurement"),
    ("a-measurement", _sample("S1"), "wrong_kind"),
]


@pytest.mark.parametrize(
    "sample, reason", [c[1:] for c in TRACK_CASES], ids=[c[0] for c in TRACK_CASES]
)
def test_local_track_verdicts(loop, sample, reason):
    got: dict = {}
    waiting = {"S1", "S2"}
    loop._take(sample, 0, 5, waiting, got, usable_track, msg.LocalTrack)
    if reason is None:
        assert set(got) == {"S1"} and not loop.stats.rejected
    else:
        assert got == {} and dict(loop.stats.rejected) == {reason: 1}
