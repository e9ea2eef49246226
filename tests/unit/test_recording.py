"""The MCAP recording: round trip (also of garbage), reading a file cut anywhere (a SIGKILLed
recorder), damage, metadata, and the run key expression the recorder subscribes to."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from mcap.reader import make_reader

from covnet.covariance_control.config import config_hash
from covnet.runs.recording import (
    META_CONFIG,
    META_RUN,
    RecordedSample,
    RecordingReader,
    RecordingWriter,
    key_kind,
    read_metadata,
    read_recording,
    run_metadata,
)
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, keyexpr_matches

RUN = "r1"


def _samples(n: int = 40) -> list[RecordedSample]:
    """A mix of valid messages of every kind and payloads that do not decode."""
    out: list[RecordedSample] = []
    t = 1_000_000
    for k in range(1, n + 1):
        cmd = msg.Command(scan=k, t=float(k), enabled=("S1", "S2"), t_sent_ns=t, episode=0)
        tru = msg.Truth(scan=k, t=float(k), target_ids=("T1",), states=np.ones((1, 4)) * k)
        meas = msg.Measurement(
            sensor_id="S1", scan=k, t=float(k), z=[[k, -k]], R=np.eye(2), t_sent_ns=t + 5
        )
        hb = msg.Heartbeat(role="sensor", node_id="S2", scan=k, t_sent_ns=t + 7)
        for key, m in (
            (msg.command_key(RUN, cmd.enabled), cmd),
            (msg.truth_key(RUN), tru),
            (msg.measurement_key(RUN, "S1"), meas),
            (msg.heartbeat_key(RUN, "sensor", "S2"), hb),
        ):
            t += 11
            sent = getattr(m, "t_sent_ns", t)
            out.append(RecordedSample(key, msg.encode(m), t, sent))
        t += 3
        # garbage: not msgpack, an empty payload, and a truncated message on a valid key
        out.append(RecordedSample(msg.measurement_key(RUN, "S2"), b"\xc1\x00junk", t, t))
        out.append(RecordedSample(f"covnet/{RUN}/elsewhere/x", b"", t + 1, t + 1))
        out.append(RecordedSample(msg.status_key(RUN), msg.encode(cmd)[:-3], t + 2, t + 2))
    return out


def _write(path, samples, **kw) -> RecordingWriter:
    w = RecordingWriter(path, run_id=RUN, metadata={"covnet.run": {"run_id": RUN}}, **kw)
    for s in samples:
        decodes = True
        try:
            msg.decode(s.payload)
        except msg.WireError:
            decodes = False
        w.write(s.key, s.payload, s.t_recv_ns, s.t_sent_ns if decodes else None)
    return w


def test_round_trip_keeps_every_payload_and_time(tmp_path):
    samples = _samples()
    path = tmp_path / "rec.mcap"
    _write(path, samples).close()
    assert list(read_recording(path)) == samples
    reader = RecordingReader(path)
    assert len(list(reader.samples())) == len(samples)
    assert reader.complete and not reader.truncated and reader.error is None


def test_standard_mcap_reader_sees_channels_schemas_and_times(tmp_path):
    samples = _samples(5)
    path = tmp_path / "rec.mcap"
    _write(path, samples).close()
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == len(samples)
        topics = {c.topic: c for c in summary.channels.values()}
        meas = topics[msg.measurement_key(RUN, "S1")]
        assert meas.message_encoding == "msgpack"
        assert summary.schemas[meas.schema_id].name == "covnet.Measurement"
        assert summary.schemas[meas.schema_id].encoding == ""
        assert topics[f"covnet/{RUN}/elsewhere/x"].schema_id == 0  # no builder makes it
        assert topics[msg.status_key(RUN)].metadata == {"kind": "status"}
        got = [
            (ch.topic, m.log_time, m.publish_time, m.data)
            for _, ch, m in reader.iter_messages(log_time_order=False)
        ]
    assert got == [(s.key, s.t_recv_ns, s.t_sent_ns, s.payload) for s in samples]


def test_a_file_cut_anywhere_reads_a_prefix_and_stops_cleanly(tmp_path):
    samples = _samples(30)
    path = tmp_path / "rec.mcap"
    _write(path, samples, chunk_size=512).close()
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    seen_counts = set()
    cut_records = 0
    # every 97th byte, and each cut inside the closing magic (after a complete footer)
    for n in [*range(0, len(data), 97), *range(len(data) - 8, len(data))]:
        cut.write_bytes(data[:n])
        reader = RecordingReader(cut)
        got = list(reader.samples())
        assert got == samples[: len(got)]
        assert not reader.complete and reader.error is None
        seen_counts.add(len(got))
        cut_records += reader.truncated
    assert len(seen_counts) > 10  # the chunks do arrive one by one
    assert cut_records > 0


def test_flushed_messages_survive_a_killed_writer(tmp_path):
    """What a SIGKILL leaves: the file as it is on disk while the writer is still open."""
    samples = _samples(10)
    path = tmp_path / "rec.mcap"
    w = _write(path, samples[:20])
    w.flush()
    w.write(samples[20].key, samples[20].payload, samples[20].t_recv_ns, None)  # not flushed
    snapshot = tmp_path / "killed.mcap"
    shutil.copyfile(path, snapshot)
    w.close()
    reader = RecordingReader(snapshot)
    assert list(reader.samples()) == samples[:20]
    assert not reader.complete and not reader.truncated  # ends between two records
    assert read_metadata(snapshot) == {"covnet.run": {"run_id": RUN}}


def test_flush_interval_bounds_what_stays_in_memory(tmp_path):
    samples = _samples(3)
    path = tmp_path / "rec.mcap"
    w = _write(path, samples, flush_interval_s=0.0)  # every write is flushed
    snapshot = tmp_path / "snap.mcap"
    shutil.copyfile(path, snapshot)
    w.close()
    assert list(read_recording(snapshot)) == samples


def test_a_corrupt_chunk_is_skipped_and_reported(tmp_path):
    samples = _samples(30)
    path = tmp_path / "rec.mcap"
    _write(path, samples, chunk_size=2048).close()
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) > 3
    second = chunks[1]
    data = bytearray(path.read_bytes())
    mid = second.chunk_start_offset + second.chunk_length - second.compressed_size // 2
    data[mid : mid + 8] = bytes(b ^ 0xFF for b in data[mid : mid + 8])
    path.write_bytes(bytes(data))
    reader = RecordingReader(path)
    got = list(reader.samples())
    assert reader.corrupt_chunks == [second.chunk_start_offset]
    assert reader.complete and reader.error is None
    assert 0 < len(got) < len(samples)
    assert all(s in samples for s in got)  # the other chunks are read in full


def test_metadata_records_run_and_config(tmp_path, paper):
    path = tmp_path / "rec.mcap"
    with RecordingWriter(path, run_id="abc", metadata=run_metadata("abc", paper)):
        pass
    meta = read_metadata(path)
    assert meta[META_RUN]["run_id"] == "abc"
    assert meta[META_RUN]["config_hash"] == config_hash(paper)
    assert meta[META_RUN]["seed"] == str(paper.seed)
    assert json.loads(meta[META_CONFIG]["config.json"])["name"] == paper.name
    reader = RecordingReader(path)
    assert list(reader.samples()) == []
    assert reader.metadata == meta and reader.complete


def test_writing_after_close_is_an_error(tmp_path):
    w = RecordingWriter(tmp_path / "r.mcap", run_id=RUN)
    w.close()
    w.close()  # idempotent
    with pytest.raises(ValueError, match="closed"):
        w.write(msg.truth_key(RUN), b"x", 1, None)


def test_key_kinds_follow_the_key_builders():
    assert key_kind(RUN, msg.truth_key(RUN)) == "truth"
    assert key_kind(RUN, msg.command_key(RUN, ["S1", "S3"])) == "cmd"
    assert key_kind(RUN, msg.command_key(RUN, [])) == "cmd"
    assert key_kind(RUN, msg.measurement_key(RUN, "S7")) == "meas"
    assert key_kind(RUN, msg.track_key(RUN)) == "track"
    assert key_kind(RUN, msg.status_key(RUN)) == "status"
    assert key_kind(RUN, msg.heartbeat_key(RUN, "world", "world")) == "hb"
    assert key_kind(RUN, msg.truth_key("other")) is None
    assert key_kind(RUN, f"covnet/{RUN}/sensor/S1/meas/extra") is None
    # a peer node's Track and Status: they were foreign keys (no schema, counted against
    # MAX_FOREIGN_CHANNELS: a network of 512 peers went partly unrecorded)
    assert key_kind(RUN, msg.peer_track_key(RUN, "S2")) == "track"
    assert key_kind(RUN, msg.peer_status_key(RUN, "S2")) == "status"
    assert key_kind(RUN, f"covnet/{RUN}/peer/S2/other") is None
    assert key_kind(RUN, msg.peer_track_key("other", "S2")) is None


def test_every_key_builder_of_a_message_has_its_channel_kind():
    """The "Adding a message" recipe says the recording names a channel from its key: every
    key builder of :mod:`covnet.wire.messages` that makes a message key is in ``key_kind``."""
    keys = {
        msg.truth_key(RUN), msg.command_key(RUN, ["S1"]), msg.measurement_key(RUN, "S1"),
        msg.track_key(RUN), msg.status_key(RUN), msg.heartbeat_key(RUN, "sensor", "S1"),
        msg.peer_track_key(RUN, "S1"), msg.peer_status_key(RUN, "S1"),
    }  # fmt: skip
    # every message key builder is among these (a new one must be added here and to key_kind;
    # alive_key, done_key and failed_key make liveliness tokens, not message keys)
    builders = {n for n in dir(msg) if n.endswith("_key") and not n.startswith("parse_")}
    assert builders - {"alive_key", "done_key", "failed_key"} == {
        "truth_key", "command_key", "measurement_key", "track_key", "status_key",
        "heartbeat_key", "peer_track_key", "peer_status_key",
    }  # fmt: skip
    missing = [k for k in keys if key_kind(RUN, k) is None]
    assert missing == []


def test_run_keyexpr_matches_every_key_of_the_run_and_nothing_else():
    expr = msg.run_keyexpr(RUN)
    assert expr == f"covnet/{RUN}/**"
    for key in (
        msg.truth_key(RUN),
        msg.command_key(RUN, ["S1"]),
        msg.measurement_key(RUN, "S1"),
        msg.track_key(RUN),
        msg.status_key(RUN),
        msg.heartbeat_key(RUN, "recorder", "recorder"),
    ):
        assert keyexpr_matches(expr, key)
    assert not keyexpr_matches(expr, msg.truth_key("r2"))
    with pytest.raises(ValueError):
        msg.run_keyexpr("bad/run")
    bus = InMemoryBus()
    try:
        sub = bus.subscribe(expr)
        bus.publish(msg.measurement_key(RUN, "S3"), b"p")
        bus.publish(msg.truth_key("r2"), b"q")
        s = sub.recv(1.0)
        assert s is not None and s.payload == b"p" and sub.try_recv() is None
    finally:
        bus.close()


def test_not_an_mcap_file_reads_nothing_and_says_why(tmp_path):
    path = tmp_path / "junk.mcap"
    path.write_bytes(b"this is not an MCAP file at all")
    reader = RecordingReader(path)
    assert list(reader.samples()) == []
    assert reader.error is not None and "byte 0" in reader.error
    assert read_metadata(path) == {}


@pytest.mark.parametrize("chunk_size", [300, 4096, 1024 * 1024])
def test_direct_message_path_writes_the_library_s_file_byte_for_byte(tmp_path, chunk_size):
    """The writer puts message records into the chunk itself (``RecordingWriter._add``); the
    file is the one the ``mcap`` library's ``add_message`` writes: same bytes, chunk
    boundaries, indexes and statistics included (small chunks: many chunk closes; out-of-order
    receive times: the start/end times), also with a flush and visual-free channels between."""
    samples = _samples(30)
    samples[7], samples[3] = samples[3], samples[7]  # log times not monotonic
    paths = []
    for direct in (True, False):
        path = tmp_path / f"rec-{direct}.mcap"
        w = RecordingWriter(path, run_id=RUN, chunk_size=chunk_size, flush_interval_s=1e6)
        assert w._fast is not None
        if not direct:
            w._fast = None
        for i, s in enumerate(samples):
            w.write(s.key, s.payload, s.t_recv_ns, s.t_sent_ns)
            if i == 50:
                w.flush()
        w.close()
        paths.append(path)
    assert paths[0].read_bytes() == paths[1].read_bytes()
    assert list(read_recording(paths[0])) == samples


def test_a_flood_of_new_keys_does_not_use_up_the_channel_ids(tmp_path, monkeypatch):
    """MCAP channel ids are 16-bit; a rogue client's puts on 70 000 distinct keys of the run
    ended the recorder in ``struct.error`` (ushort format).  Keys of no covnet layout get at
    most MAX_FOREIGN_CHANNELS channels, every key at most MAX_KEY_CHANNELS; a message on a new
    key beyond them is not recorded (``write`` says so), and the file stays whole."""
    from covnet.runs import recording

    monkeypatch.setattr(recording, "MAX_KEY_CHANNELS", 1500)
    path = tmp_path / "rec.mcap"
    w = RecordingWriter(path, run_id=RUN)
    written = [w.write(f"covnet/{RUN}/junk/k{i}", b"x", i + 1, None) for i in range(70_000)]
    assert sum(written) == recording.MAX_FOREIGN_CHANNELS and all(written[:1024])
    assert w.write(f"covnet/{RUN}/junk/k0", b"y", 80_000, None)  # a known key: recorded
    legit = [w.write(msg.measurement_key(RUN, f"S{i}"), b"z", 90_000 + i, None) for i in range(600)]
    assert sum(legit) == 1500 - recording.MAX_FOREIGN_CHANNELS
    w.close()
    got = list(read_recording(path))
    assert len(got) == recording.MAX_FOREIGN_CHANNELS + 1 + 1500 - recording.MAX_FOREIGN_CHANNELS
    with open(path, "rb") as f:
        assert len(make_reader(f).get_summary().channels) == 1500


def test_keys_naming_nodes_the_run_does_not_have_are_foreign(tmp_path, monkeypatch):
    """A rogue's puts on covnet-shaped keys naming made-up nodes (``cmd/~Z17~``,
    ``sensor/S9999/meas``, ``hb/sensor/X``, ``peer/Q/track``) counted as the run's own: 66 000 of
    them used up every channel and the manager's later commands went unrecorded, while the
    replay said ``identical``.  With the run's sensors known they are foreign (capped), the
    run's own keys keep their channels, and what was not recorded is in the recording."""
    from covnet.runs import recording
    from covnet.runs.replay_kit import recording_notes

    monkeypatch.setattr(recording, "MAX_KEY_CHANNELS", 1500)
    path = tmp_path / "rec.mcap"
    w = RecordingWriter(path, run_id=RUN, sensors=("S1", "S2"))
    rogue = [
        *(msg.command_key(RUN, [f"Z{i}"]) for i in range(700)),
        *(msg.command_key(RUN, ["S1", f"Z{i}"]) for i in range(300)),
        *(msg.measurement_key(RUN, f"S{i + 3}") for i in range(300)),
        *(msg.heartbeat_key(RUN, "sensor", f"X{i}") for i in range(200)),
        *(msg.heartbeat_key(RUN, "world", f"W{i}") for i in range(100)),
        *(msg.peer_track_key(RUN, f"Q{i}") for i in range(100)),
    ]
    written = [w.write(k, b"x", i + 1, None) for i, k in enumerate(rogue)]
    assert sum(written) == recording.MAX_FOREIGN_CHANNELS
    own = [
        msg.command_key(RUN, []),
        msg.command_key(RUN, ["S1", "S2"]),
        msg.measurement_key(RUN, "S2"),
        msg.heartbeat_key(RUN, "sensor", "S1"),
        msg.heartbeat_key(RUN, msg.WORLD_ID, msg.WORLD_ID),
        msg.heartbeat_key(RUN, msg.MANAGER_ID, msg.MANAGER_ID),
        msg.peer_status_key(RUN, "S2"),
        msg.track_key(RUN),
    ]
    assert all(w.write(k, b"y", 10_000 + i, None) for i, k in enumerate(own))
    assert w.unrecorded == len(rogue) - recording.MAX_FOREIGN_CHANNELS
    w.close()
    reader = RecordingReader(path)
    assert len(list(reader.samples())) == recording.MAX_FOREIGN_CHANNELS + len(own)
    assert reader.metadata[recording.META_UNRECORDED] == {
        "no_channel": str(len(rogue) - recording.MAX_FOREIGN_CHANNELS),
        "first_key": rogue[recording.MAX_FOREIGN_CHANNELS],
    }
    (note,) = [n for n in recording_notes(reader, {}) if "not recorded" in n]
    assert str(len(rogue) - recording.MAX_FOREIGN_CHANNELS) in note
    with open(path, "rb") as f:  # the official reader takes the record at the end
        assert make_reader(f).get_summary().statistics.metadata_count == 1


def test_a_sensor_key_carrying_local_tracks_is_named_so(tmp_path):
    """With the info, ci and peer rules a sensor's key carries its LocalTrack: the channel was
    named ``meas`` (schema ``covnet.Measurement``) whatever it carried; the first payload names
    it now.  A Measurement on it is still ``meas``."""
    path = tmp_path / "rec.mcap"
    lt = msg.LocalTrack(
        sensor_id="S1", scan=1, t=1.0, x=np.zeros(4), P=np.eye(4), x_prior=np.zeros(4),
        P_prior=np.eye(4), t_sent_ns=5, episode=0,
    )  # fmt: skip
    m = msg.Measurement("S2", 1, 1.0, np.zeros((1, 2)), np.eye(2), 5, seq=1)
    with RecordingWriter(path, run_id=RUN) as w:
        w.write(msg.measurement_key(RUN, "S1"), msg.encode(lt), 10, 5)
        w.write(msg.measurement_key(RUN, "S2"), msg.encode(m), 11, 5)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    topics = {c.topic: c for c in summary.channels.values()}
    local, meas = topics[msg.measurement_key(RUN, "S1")], topics[msg.measurement_key(RUN, "S2")]
    assert local.metadata == {"kind": "ltrack"} and meas.metadata == {"kind": "meas"}
    assert summary.schemas[local.schema_id].name == "covnet.LocalTrack"
