"""A sensor's measurement from its template (:mod:`covnet.wire.batch_encode`, issue 29) against
the codec: the same bytes as ``encode(Measurement(...))`` for any valid values, at every
msgpack int width, and ``None`` (the codec's path, which then refuses) for any value the
constructor would refuse or convert; a covariance sensor's fast path
(:func:`sensors.covariance.fast_respond`) against its ``respond`` and the codec, over scans and
episodes; and a sensor's protocol state (:class:`sensors.protocol._Sensor`) publishing the same
payloads with and without it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet import kinds
from covnet.config import NetworkSpec
from covnet.covariance_control.model import build_model
from covnet.covariance_control.sensor_side import SensorSide
from covnet.wire import messages as msg
from covnet.wire.batch_encode import MeasurementTemplate
from covnet.wire.bus import InMemoryBus
from sensors.covariance import NoiseTable, _wire, fast_respond
from sensors.protocol import _Sensor

# every msgpack int width's edges: fixint, uint8, uint16, uint32, uint64
_EDGES = [0, 1, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**63 - 1]
ints = st.one_of(st.sampled_from(_EDGES), st.integers(0, 2**63 - 1))
finite = st.floats(allow_nan=False, allow_infinity=False)
names = st.sampled_from(["S1", "S12", "s", "A" * 60, "S1.10", "x_y-z", "sensor-0042"])


def _R(dz: int, values: list[float]) -> np.ndarray:
    return np.array(values[: dz * dz], dtype=float).reshape(dz, dz)


@settings(max_examples=400, deadline=None)
@given(
    sid=names,
    dz=st.integers(1, 3),
    rvals=st.lists(finite, min_size=9, max_size=9),
    zvals=st.lists(finite, min_size=3, max_size=3),
    scan=ints,
    t=finite,
    t_sent=ints,
    episode=ints,
    seq=ints,
)
def test_the_template_writes_the_codecs_bytes(sid, dz, rvals, zvals, scan, t, t_sent, episode, seq):
    R = _R(dz, rvals)
    z = np.array([zvals[:dz]])
    tpl = MeasurementTemplate.of(sid, R)
    assert tpl is not None
    want = msg.encode(msg.Measurement(sid, scan, t, z, R, t_sent, episode=episode, seq=seq))
    assert tpl.encode(scan, t, z, t_sent, episode, seq) == want


def _refused(sid, R, scan, t, z, t_sent, episode, seq) -> bool:
    try:
        msg.Measurement(sid, scan, t, z, R, t_sent, episode=episode, seq=seq)
    except msg.WireError:
        return True
    return False


_GOOD = (7, 0.5, np.array([[1.0, 2.0]]), 10, 0, 3)


@pytest.mark.parametrize(
    "at, value",
    [
        (0, -1), (0, 2**63), (0, True), (0, np.int64(7)), (0, 7.0),
        (1, math.nan), (1, math.inf), (1, -math.inf), (1, 1), (1, np.float64(0.5)),
        (2, np.array([[math.nan, 1.0]])), (2, np.array([[1.0, math.inf]])),
        (2, np.array([1.0, 2.0])), (2, np.array([[1.0, 2.0, 3.0]])),
        (2, np.array([[1.0, 2.0]], dtype=np.float32)), (2, [[1.0, 2.0]]),
        (2, np.array([[1.0], [2.0]])), (2, np.zeros((2, 2))),
        (3, -5), (3, 2**64), (4, -1), (4, False), (5, -1), (5, None),
    ],
)  # fmt: skip
def test_the_template_declines_what_it_does_not_check(at, value):
    """Anything outside exact ints in [0, 2**63), a finite float ``t`` and a finite float64
    ``(1, dz)`` ``z``: ``None``, so the caller builds the message (which refuses the invalid
    ones, and converts the others to the values the template then takes)."""
    R = np.eye(2)
    tpl = MeasurementTemplate.of("S1", R)
    assert tpl is not None
    args = list(_GOOD)
    args[at] = value
    assert tpl.encode(*args) is None
    scan, t, z, t_sent, episode, seq = args
    if at == 2 and isinstance(value, np.ndarray) and not np.all(np.isfinite(value)):
        assert _refused("S1", R, scan, t, z, t_sent, episode, seq)


def test_a_template_of_an_invalid_sensor_is_refused_as_the_message_is():
    with pytest.raises(msg.WireError):
        MeasurementTemplate.of("bad id/with slash", np.eye(2))
    with pytest.raises(msg.WireError):
        MeasurementTemplate.of("S1", np.array([[1.0, math.nan], [0.0, 1.0]]))


class _Clock:
    """A clock whose ``now_ns`` counts up by 1000 from a start (both paths read it once a
    measurement)."""

    def __init__(self, start: int) -> None:
        self.t = start

    def now_ns(self) -> int:
        self.t += 1000
        return self.t

    def now(self) -> float:
        return self.t / 1e9

    def sleep_until(self, t: float) -> None:  # pragma: no cover
        pass


def _scenario(tmp_path, n: int):
    kind, sc0 = kinds.load("configs/paper.yaml")
    make = kinds.command(kind, "bench:up-config", "a bench network of N sensors")
    path = tmp_path / f"n{n}.yaml"
    path.write_text(yaml.safe_dump(make(sc0, n, 60), sort_keys=False))
    return kinds.load(path)[1]


@pytest.mark.parametrize(
    "config, noise",
    [
        ("configs/paper.yaml", "table"), ("bench-12", "table"), ("configs/paper.yaml", "draw"),
        ("configs/paper.yaml", "table with gaps"),
    ],
)  # fmt: skip
def test_a_covariance_sensors_fast_path_sends_its_respond_bytes(tmp_path, config, noise):
    """``fast_respond`` against ``sensors.covariance.run``'s ``respond`` + ``evolve(seq)`` +
    the codec: every sensor, every scan, two episodes, the clock read the same; its noise
    drawn ahead (``NoiseTable``, as the sensor process does), drawn per scan (the sensor
    side's default), or from a table missing every third scan (the fast path draws those, as
    past the end of a table)."""
    sc = kinds.load(config)[1] if config.endswith(".yaml") else _scenario(tmp_path, 12)
    model = build_model(sc)
    rng = np.random.default_rng(5)
    for j in range(len(model.sensor_ids)):
        table = NoiseTable(model, j) if noise != "draw" else None
        if noise == "table with gaps":
            assert table is not None
            table.table = {k: v for k, v in table.table.items() if k % 3}
        side_a = SensorSide.of_process(sc, model, j, table)
        side_b = SensorSide.of_process(sc, model, j, NoiseTable(model, j))
        clock_a, clock_b = _Clock(10**12 + j), _Clock(10**12 + j)
        fast = fast_respond(side_a, clock_a)  # type: ignore[arg-type]
        assert fast is not None
        seq = 0
        for episode in (0, 1):
            for scan in range(1, min(model.scans, 60) + 1):
                states = rng.normal(0.0, 1e3, (1, 4))
                cmd = msg.Command(scan, scan * 0.5, (model.sensor_ids[j],), 5, episode=episode)
                tr = msg.Truth(scan, scan * 0.5, ("T1",), states)
                seq += 1
                got = fast(cmd, tr, seq)
                m = side_b.respond(cmd.episode, cmd.scan, None, truth=tr.states[0])
                want = msg.encode(_wire(m, cmd, clock_b).evolve(seq=seq))  # type: ignore[arg-type]
                assert got == want


def test_no_fast_path_under_a_track_rule(tmp_path):
    with open("configs/paper.yaml") as f:
        raw = yaml.safe_load(f)
    raw.setdefault("fusion", {})["mode"] = "info"
    path = tmp_path / "info.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    sc = kinds.load(path)[1]
    model = build_model(sc)
    side = SensorSide.of_process(sc, model, 0, NoiseTable(model, 0))
    assert fast_respond(side, _Clock(0)) is None  # type: ignore[arg-type]


def test_a_sensor_publishes_the_same_payloads_with_and_without_its_fast_path():
    """The protocol state of one sensor answering commands (``_Sensor.answer``), with the fast
    path and without: the same payloads on the same key, the same counters."""
    sc = kinds.load("configs/paper.yaml")[1]
    model = build_model(sc)
    j = 2
    out = []
    for use_fast in (True, False):
        bus = InMemoryBus()
        sub = bus.subscribe(msg.measurement_keyexpr("run1"))
        side = SensorSide.of_process(sc, model, j, NoiseTable(model, j))
        clock = _Clock(10**9)

        def respond(cmd, tr, side=side, clock=clock):
            m = side.respond(cmd.episode, cmd.scan, None, truth=tr.states[0])
            return _wire(m, cmd, clock)

        one = _Sensor(
            model.sensor_ids[j], bus, "run1", clock, NetworkSpec(),  # type: ignore[arg-type]
            truth_ok=lambda tr: True, respond=respond, scans=30, missed_command=None,
            keep_truth=True,
            command_ok=None, fast=fast_respond(side, clock) if use_fast else None,  # type: ignore[arg-type]
        )  # fmt: skip
        got = []
        for scan in range(1, 30):
            states = np.array([[100.0 * scan, -3.0, 1.5, 2.0]])
            one.take_truth(msg.Truth(scan, scan * 1.0, ("T1",), states))
            one.accept(msg.Command(scan, scan * 1.0, (model.sensor_ids[j],), 5, episode=0))
            one.answer(lambda stage: None)
            while (s := sub.try_recv()) is not None:
                got.append((s.key, s.payload))
        out.append((got, one.stats.measurements_sent, one.stats.enabled_scans))
    assert out[0] == out[1]
    assert out[0][1] == 29 and len(out[0][0]) == 29
