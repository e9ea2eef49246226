"""The replay kit (:mod:`covnet.runs.replay_kit`) and each kind's replay: a recorded in-process
network of each kind (world, sensors, recorder and manager loops of the kind's own roles, as
threads over one InMemoryHub) replays identically, and one tampered measurement or decision in
its recording is reported as a difference."""

from __future__ import annotations

import importlib
import threading
from dataclasses import replace
from pathlib import Path

import pytest
import yaml

from covnet import kinds
from covnet.clock import WallClock
from covnet.covariance_control import replay as cc_replay
from covnet.covariance_control.results import write_network_run as cc_write
from covnet.mobile import replay as mobile_replay
from covnet.mobile.network import write_network_run as mobile_write
from covnet.passive import replay as passive_replay
from covnet.passive.network import write_network_run as passive_write
from covnet.runs.recording import (
    RecordingReader,
    RecordingWriter,
    key_kind,
    read_metadata,
    run_metadata,
)
from covnet.runs.replay_kit import (
    MAX_LISTED,
    RECORDING,
    Differences,
    compare_file,
    failure_events,
)
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, InMemoryHub
from recorder import node as recorder_node

RUN = "rk"
CONFIGS = Path(__file__).resolve().parents[2] / "configs"
CASES = {
    "covariance_control": (
        CONFIGS / "paper.yaml",
        {"scans": 6, "allocation": {"metrics": ["spectral"]}},
        cc_write,
        cc_replay.replay_run,
    ),
    "mobile": (CONFIGS / "mobile.yaml", {"scans": 5}, mobile_write, mobile_replay.replay_run),
    "passive": (CONFIGS / "passive.yaml", {}, passive_write, passive_replay.replay_run),
}
"""kind -> (shipped config, changes that keep it short, the manager's writer, the replay)."""


# --------------------------------------------------------------------------------------------
# the kit's own parts
# --------------------------------------------------------------------------------------------


def test_differences_are_listed_up_to_a_limit_per_kind_and_the_rest_counted():
    d = Differences()
    for i in range(MAX_LISTED + 3):
        d.add("track", f"t{i}")
    d.add("value", "v")
    out = d.finish()
    assert out[:MAX_LISTED] == [f"t{i}" for i in range(MAX_LISTED)]
    assert out[MAX_LISTED:] == ["v", "... and 3 more differences of kind 'track'"]


def test_compare_file_names_the_differing_json_paths_shallowest_first(tmp_path):
    a, b = tmp_path / "a" / "summary.json", tmp_path / "b" / "summary.json"
    a.parent.mkdir(), b.parent.mkdir()
    a.write_text('{"x": {"y": [1, 2]}, "z": 1.5}')
    b.write_text('{"x": {"y": [1, 3]}, "z": 1.25}')
    d = Differences()
    compare_file(a, b, d)
    assert d.finish() == [
        "summary.json z: 1.5 (original) != 1.25 (replayed)",
        "summary.json x.y[1]: 2 (original) != 3 (replayed)",
    ]
    b.write_text('{"x": {"y": [1, 2]},\n "z": 1.5}')  # same data, other bytes
    d = Differences()
    compare_file(a, b, d)
    assert d.finish() == ["summary.json: same content but different bytes (format/order)"]
    d = Differences()
    compare_file(a, tmp_path / "none.json", d)
    assert len(d.finish()) == 1


def test_failure_events_from_two_successive_failed_sets():
    assert failure_events(frozenset({"S1"}), frozenset({"S2"}), 4) == [
        {"sensor": "S1", "scan": 4, "event": "rejoined"},
        {"sensor": "S2", "scan": 4, "event": "failed"},
    ]


# --------------------------------------------------------------------------------------------
# each kind: a recorded in-process network
# --------------------------------------------------------------------------------------------


def _config(name):
    path, changes, _, _ = CASES[name]
    data = yaml.safe_load(path.read_text())
    for key, value in changes.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) else value
    return kinds.from_dict(data, str(path), path.parent)


def _record(name, out):
    """The kind's network in threads (its registered roles), recorded into ``out``, and the
    manager's run directory written there by its own writer."""
    kind, cfg = _config(name)
    role = {r: importlib.import_module(m) for r, m in kind.roles.items()}
    out.mkdir(parents=True)
    hub = InMemoryHub()
    stops: list[threading.Event] = []
    threads: list[threading.Thread] = []

    def start(node, target):
        ev, bus = threading.Event(), InMemoryBus(hub, name=node)
        stops.append(ev)

        def body():
            try:
                target(bus, ev)
            finally:
                bus.close()

        threads.append(threading.Thread(target=body, name=node, daemon=True))
        threads[-1].start()

    writer = RecordingWriter(out / RECORDING, run_id=RUN, metadata=run_metadata(RUN, cfg))
    try:
        start("recorder", lambda b, ev: recorder_node.run(cfg, b, RUN, WallClock(), ev, writer))
        start("world", lambda b, ev: role["world"].run(cfg, b, RUN, WallClock(), ev))
        for sid in cfg.sensor_ids:
            start(sid, lambda b, ev, sid=sid: role["sensor"].run(cfg, sid, b, RUN, WallClock(), ev))
        mbus = InMemoryBus(hub, name="manager")
        try:
            result = role["manager"].run(cfg, mbus, RUN, WallClock(), threading.Event())
        finally:
            mbus.close()
            for ev in stops:
                ev.set()
            for th in threads:
                th.join(timeout=10)
    finally:
        writer.close()
    assert result.completed and result.error is None
    CASES[name][2](out, cfg, result, {"run_id": RUN})
    return cfg


@pytest.fixture(scope="module", params=sorted(CASES))
def recorded(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(request.param) / "run"
    return request.param, out, _record(request.param, out)


def _rewrite(src, dst, change):
    """``src``'s recording copied into ``dst``, each sample's payload passed through
    ``change(sample) -> payload``."""
    dst.mkdir()
    for f in src.iterdir():
        if f.is_file() and f.name != RECORDING:
            (dst / f.name).write_bytes(f.read_bytes())
    with RecordingWriter(dst / RECORDING, run_id=RUN, metadata=read_metadata(src / RECORDING)) as w:
        for s in RecordingReader(src / RECORDING).samples():
            w.write(s.key, change(s), s.t_recv_ns, s.t_sent_ns)


def _fused_at(run, scan):
    """The recorded Status of ``scan`` and the first sensor it fused with a non-empty ``z``."""
    samples = list(RecordingReader(run / RECORDING).samples())
    status = next(
        st
        for s in samples
        if s.key == msg.status_key(RUN)
        and (st := msg.decode_as(s.payload, msg.Status)).scan == scan
    )
    for s in samples:
        if key_kind(RUN, s.key) == msg.Measurement.KIND:
            m = msg.decode_as(s.payload, msg.Measurement)
            if m.scan == scan and m.sensor_id in status.fused and m.z.shape[0]:
                return status, m
    raise AssertionError(f"no fused measurement with a detection at scan {scan}")


def test_the_replay_of_a_recorded_network_is_identical(recorded, tmp_path):
    name, run, _ = recorded
    report = CASES[name][3](run, tmp_path / "replay")
    assert report.identical, report.differences
    assert report.counts["status"] >= 1 and report.notes == []


def test_a_tampered_measurement_is_reported(recorded, tmp_path):
    """One coordinate of one fused detection moved by 1e-3 (m or rad): the recomputed track is
    not the recorded one, and the result file differs."""
    name, run, _ = recorded
    _, m = _fused_at(run, 2)
    key = msg.measurement_key(RUN, m.sensor_id)

    def change(s):
        if s.key != key:
            return s.payload
        got = msg.decode_as(s.payload, msg.Measurement)
        if got.scan != 2:
            return s.payload
        z = got.z.copy()
        z[0, 0] += 1e-3
        return msg.encode(replace(got, z=z))

    _rewrite(run, tmp_path / "run", change)
    report = CASES[name][3](tmp_path / "run")
    assert not report.identical
    text = "\n".join(report.differences)
    assert "scan 2: replayed estimate" in text and "differs from the recorded Track" in text, text
    compared = "association.json" if name == "passive" else "summary.json"
    assert any(d.startswith(f"{compared} ") for d in report.differences), text


def test_a_tampered_decision_is_reported(recorded, tmp_path):
    """The recorded Status of scan 2 names one sensor fewer than the manager enabled."""
    name, run, _ = recorded

    def change(s):
        if s.key != msg.status_key(RUN):
            return s.payload
        st = msg.decode_as(s.payload, msg.Status)
        return msg.encode(replace(st, enabled=st.enabled[:-1])) if st.scan == 2 else s.payload

    _rewrite(run, tmp_path / "run", change)
    report = CASES[name][3](tmp_path / "run")
    assert not report.identical
    assert any("scan 2: replayed allocation" in d for d in report.differences), report.differences


def test_a_measurement_on_a_key_with_an_invalid_sensor_id_is_skipped_not_a_crash():
    """A well-formed Measurement on ``covnet/<run>/sensor/<65 X>/meas`` (the manager counts it
    ``bad_key``) ended ``covnet replay`` in a ValueError from the key's parser."""
    import numpy as np

    from covnet.runs.recording import RecordedSample
    from covnet.runs.replay_kit import load_recording

    run = "r1"
    good = msg.Measurement("S1", 3, 3.0, np.zeros((1, 2)), np.eye(2), 5, seq=3)
    payload = msg.encode(good)
    samples = [
        RecordedSample(f"covnet/{run}/sensor/{'X' * 65}/meas", payload, 1, 1),
        RecordedSample(msg.measurement_key(run, "S1"), payload, 2, 2),
    ]
    rec = load_recording(iter(samples), run)
    assert rec.counts["skipped:bad_key"] == 1
    assert list(rec.meas) == [(good.episode, 3, "S1")]


def test_a_second_status_of_a_scan_is_named_in_the_notes(tmp_path):
    """A forged Status recorded before the manager's made the replay report differences with
    nothing to say why (the replay takes the first Status of a scan): the notes now say that
    a scan has more than one, which the manager never sends."""
    from covnet.runs.replay_kit import load_recording, recording_notes

    run = "r2"
    path = tmp_path / "rec.mcap"
    w = RecordingWriter(path, run_id=run)
    for i, value in enumerate((9.0, 1.0)):  # the forger's first, then the manager's
        st = msg.Status(3, 3.0, ("S1",), 2.0, 1.0, value, 1, 0, (), ("S1",))
        w.write(msg.status_key(run), msg.encode(st), 10 + i, None)
    w.close()
    reader = RecordingReader(path)
    rec = load_recording(reader.samples(), run)
    assert rec.status[(0, 3)].value == 9.0 and rec.counts["status_duplicate"] == 1
    notes = recording_notes(reader, rec.counts)
    assert any(n.startswith("1 scan(s) have more than one Status recorded") for n in notes)


def test_a_recording_s_keys_are_classified_once_each(monkeypatch):
    """``load_recording`` works out each distinct key's kind once (a 256-sensor replay spent a
    quarter of its time on the same keys), and keeps what it kept before: the same Status,
    measurements and counts as classifying every sample."""
    import numpy as np

    from covnet.runs import replay_kit
    from covnet.runs.recording import RecordedSample

    run = "r1"
    samples = []
    for k in range(1, 6):
        for sid in ("S1", "S2", "S3"):
            m = msg.Measurement(sid, k, float(k), np.full((1, 2), k + 0.5), np.eye(2), 5, seq=k)
            samples.append(RecordedSample(msg.measurement_key(run, sid), msg.encode(m), k, k))
        samples.append(RecordedSample(f"covnet/{run}/rogue/key", b"\x80", k, k))
    real = replay_kit.key_kind
    calls: list[str] = []

    def counting(run_id: str, key: str, sensors=None):
        calls.append(key)
        return real(run_id, key, sensors)

    monkeypatch.setattr(replay_kit, "key_kind", counting)
    rec = replay_kit.load_recording(iter(samples), run)
    assert sorted(calls) == sorted(set(calls)) and len(calls) == 4
    assert rec.counts["samples"] == 20 and rec.counts["measurement"] == 15
    assert sorted(rec.meas) == [(0, k, sid) for k in range(1, 6) for sid in ("S1", "S2", "S3")]
