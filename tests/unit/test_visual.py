"""The visual channels (:mod:`covnet.runs.visual` and each kind's ``visual`` module): oracle values
of
the geometry, colours by sensor state, counts per scan, and every message of a ``covnet run
--mcap`` file decoded with the official readers (``mcap`` + ``mcap-protobuf-support`` for the
Foxglove protobuf schemas, ``jsonschema`` for the numbers)."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import yaml
from foxglove_jsonschema import message_problems, schema_problems
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from covnet import kinds
from covnet.cli.app import main as covnet_main
from covnet.runs.recording import RecordingReader
from covnet.runs.visual import (
    COLOURS,
    LOG_TOPIC,
    METRICS_TOPIC,
    SCENE_SCHEMA,
    SCENE_TOPIC,
    Coverage,
    Estimate,
    SensorView,
    View,
    Visualiser,
    ellipse_axes,
    ellipse_points,
    scene_update,
    sensor_states,
)
from covnet.wire import messages as msg

ROOT = Path(__file__).resolve().parents[2]


def _decoded(path: Path, topics=(SCENE_TOPIC, LOG_TOPIC)):
    """``(topic, schema name, decoded)`` of every protobuf visual message (official reader)."""
    with open(path, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        return [
            (ch.topic, schema.name, dec)
            for schema, ch, _, dec in r.iter_decoded_messages(topics=list(topics))
        ]


def _metrics(path: Path) -> list[dict]:
    """Every ``/covnet/scan`` message, validated against the JSON Schema the file holds, which
    Foxglove's parser accepts (and the message holds no null)."""
    out = []
    with open(path, "rb") as f:
        r = make_reader(f)
        for schema, ch, m in r.iter_messages(topics=[METRICS_TOPIC]):
            assert schema.encoding == "jsonschema" and ch.message_encoding == "json"
            assert schema_problems(json.loads(schema.data)) == []
            assert message_problems(m.data) == []
            doc = json.loads(m.data)
            jsonschema.validate(doc, json.loads(schema.data))
            out.append(doc)
    return out


# ---- geometry --------------------------------------------------------------------------------


@pytest.mark.parametrize("n_sigma", [1.0, 2.0], ids=["1sigma", "2sigma"])
def test_ellipse_axes_are_the_eigen_decomposition(n_sigma):
    C = np.array([[4.0, 1.5], [1.5, 2.0]])
    lam = np.linalg.eigvalsh(C)  # (3 - sqrt(1 + 2.25*4... ) written out: eig of C
    axes, V = ellipse_axes(C, n_sigma)
    np.testing.assert_allclose(axes, n_sigma * np.sqrt(lam))
    np.testing.assert_allclose(V @ np.diag(lam) @ V.T, C, atol=1e-12)
    pts = ellipse_points((10.0, -5.0, 0.0), C, n_sigma, n=64)
    d = pts - [10.0, -5.0]
    # every point is on the n-sigma contour: d' C^-1 d = n^2
    np.testing.assert_allclose(np.einsum("ij,jk,ik->i", d, np.linalg.inv(C), d), n_sigma**2)
    # and the farthest is the major semi-axis n sqrt(lambda_max) away
    assert np.linalg.norm(d, axis=1).max() == pytest.approx(n_sigma * np.sqrt(lam[-1]), rel=1e-3)


def test_diagonal_covariance_ellipse_axes():
    axes, _ = ellipse_axes(np.diag([25.0, 9.0]), 2.0)
    np.testing.assert_allclose(axes, [6.0, 10.0])  # 2 * sqrt(9), 2 * sqrt(25), ascending


# ---- the scene -------------------------------------------------------------------------------


def _status(enabled, failed=(), scan=1):
    return msg.Status(
        scan=scan, t=float(scan), enabled=tuple(enabled), trace_P=1.0, trace_Pd=2.0, value=0.5,
        t_sent_ns=0, failed=tuple(failed),
    )  # fmt: skip


def test_sensor_states():
    st = _status(["S1", "S3"], failed=["S2"])
    assert sensor_states(st, ["S1", "S2", "S3", "S4"]) == {
        "S1": "on",
        "S2": "failed",
        "S3": "on",
        "S4": "off",
    }


def _scene_view():
    view = View(frame="world_m", marker=2.0)
    view.truths = [("T1", (1.0, 2.0, 0.0))]
    view.estimates = [
        Estimate("T1", (1.5, 2.5, 0.0), cov_xy=np.diag([4.0, 1.0]), desired_xy=np.eye(2))
    ]
    view.sensors = [
        SensorView("S1", (0.0, 0.0, 0.0), "on", Coverage(100.0), ("T1",)),
        SensorView("S2", (10.0, 0.0, 0.0), "off", Coverage(100.0, 45.0, 30.0), ("T1",)),
        SensorView("S3", (20.0, 0.0, 0.0), "failed"),
    ]
    return view


def test_scene_update_entities_colours_and_lines():
    update = _decode_bytes(SCENE_SCHEMA, scene_update(_scene_view(), 5_000_000_123).encode())
    ents = {e.id: e for e in update.entities}
    assert set(ents) == {"truth/T1", "estimate/T1", "sensor/S1", "sensor/S2", "sensor/S3"}
    assert len(update.deletions) == 1  # everything of the previous scan goes first
    for sid, state in (("S1", "on"), ("S2", "off"), ("S3", "failed")):
        c = ents[f"sensor/{sid}"].cubes[0].color
        assert (c.r, c.g, c.b, c.a) == pytest.approx(COLOURS[state])
    # 1 sigma, 2 sigma and the desired ellipse, each a closed loop around the estimate
    loops = ents["estimate/T1"].lines
    assert len(loops) == 3
    got = [np.array([[p.x, p.y] for p in ln.points]) - [1.5, 2.5] for ln in loops]
    assert np.abs(got[0]).max(axis=0) == pytest.approx([2.0, 1.0], rel=1e-2)  # sqrt(4), sqrt(1)
    assert np.abs(got[1]).max(axis=0) == pytest.approx([4.0, 2.0], rel=1e-2)
    assert np.abs(got[2]).max(axis=0) == pytest.approx([1.0, 1.0], rel=1e-2)
    # S1 on: coverage + a line to the true target; S2 off: coverage only (a sector); S3 nothing
    s1 = ents["sensor/S1"].lines
    assert len(s1) == 2 and [(p.x, p.y) for p in s1[1].points] == [(0.0, 0.0), (1.0, 2.0)]
    assert len(ents["sensor/S2"].lines) == 1
    sector = ents["sensor/S2"].lines[0].points
    assert (sector[0].x, sector[0].y) == (sector[-1].x, sector[-1].y) == (10.0, 0.0)
    assert len(ents["sensor/S3"].lines) == 0
    ts = update.entities[0].timestamp
    assert (ts.seconds, ts.nanos) == (5, 123)


# ---- a stream of messages -> frames ------------------------------------------------------------


def _paper(scans=4, **changes):
    data = yaml.safe_load((ROOT / "configs" / "paper.yaml").read_text())
    data.update(scans=scans, **changes)
    return kinds.from_dict(data, "paper")


def test_one_frame_per_status_with_the_counts():
    kind, cfg = _paper(scans=3)
    vis = Visualiser(kind.visual(cfg), kind.episodes(cfg))
    x, P = np.array([426.0, 426.0, 1.0, 0.0]), np.diag([9.0, 1.0, 4.0, 1.0])
    truth = msg.Truth(scan=1, t=1.0, target_ids=("T1",), states=np.zeros((1, 4)))
    out = []
    for m in (
        truth,
        msg.Command(scan=1, t=1.0, enabled=("S1", "S3"), t_sent_ns=1_000_000),
        msg.Track(scan=1, t=1.0, x=x, P=P, t_sent_ns=3_000_000),
        msg.Status(scan=1, t=1.0, enabled=("S1", "S3"), trace_P=15.0, trace_Pd=52.8,
                   value=3.0, t_sent_ns=4_000_000, failed=("S2",)),
    ):  # fmt: skip
        out += vis.feed(m.KIND, "k", msg.encode(m), 5_000_000)
    assert [vm.topic for vm in out] == [SCENE_TOPIC, METRICS_TOPIC, LOG_TOPIC]
    doc = json.loads(out[1].data)
    assert doc["n_active"] == 2 and doc["n_failed"] == 1 and doc["messages"] == 4
    assert doc["scan_latency_ms"] == pytest.approx(3.0)
    assert doc["f"] == 3.0 and doc["trace_P"] == 15.0 and doc["trace_Pd"] == 52.8
    (t1,) = doc["targets"]
    # error and NEES against the truth at the origin: |(426, 1)|, x' P^-1 x
    assert t1["error"] == pytest.approx(np.hypot(426.0, 1.0))
    assert t1["nees"] == pytest.approx(426.0**2 / 9 + 426.0**2 + 1 / 4)
    assert t1["rmse"] == pytest.approx(t1["error"])
    assert t1["trace_Pd"] == pytest.approx(52.8)  # the paper's desired covariance of scan 1
    scene = _decode(out[0])
    assert len(scene.entities) == 1 + 1 + 8  # the truth, the estimate, 8 sensors
    sensors = [e for e in scene.entities if e.id.startswith("sensor/")]
    assert Counter(e.metadata[0].value for e in sensors) == {"on": 2, "failed": 1, "off": 5}
    links = {e.id: len(e.lines) for e in sensors}  # a paper sensor has no coverage
    assert links == {f"sensor/S{i}": int(i in (1, 3)) for i in range(1, 9)}
    log = _decode(out[2])
    assert log.level == 3 and "failed S2" in log.message  # WARNING while a sensor is failed


def _decode(vm):
    """A visual message decoded with mcap-protobuf-support, from the schema the SDK gave."""
    return _decode_bytes(vm.schema, vm.data)


def _decode_bytes(sdk_schema, data):
    schema = Schema(id=1, name=sdk_schema.name, encoding=sdk_schema.encoding, data=sdk_schema.data)
    return DecoderFactory().decoder_for("protobuf", schema)(data)


# ---- covnet run --mcap: every kind, the official readers ----------------------------------------

# config -> (changes, episodes, entities per scene besides the passive's segments)
RUNS = {
    "paper": ({"scans": 6}, 3, 1 + 1 + 8),
    "multitarget": ({"scans": 60, "allocation": {"metrics": ["spectral"]}}, 1, 3 + 3 + 12),
    "mobile": ({"scans": 5, "compare_exact": False}, 1, 3 + 3 + 4),
    "passive": ({}, 1, None),
}


@pytest.mark.parametrize("name", sorted(RUNS))
def test_run_mcap_decodes_with_the_official_readers(tmp_path, name):
    changes, episodes, entities = RUNS[name]
    data = yaml.safe_load((ROOT / "configs" / f"{name}.yaml").read_text())
    for key, value in changes.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) else value
    cfg_path = tmp_path / f"{name}.yaml"
    cfg_path.write_text(yaml.safe_dump(data))
    out = tmp_path / "run"
    assert covnet_main(["run", str(cfg_path), "--out", str(out), "--no-figures", "--mcap"]) == 0
    path = out / "run.mcap"
    scans = data.get("scans", 1) if name != "passive" else 1  # covnet run draws one passive scan
    decoded = _decoded(path)
    counts = Counter(topic for topic, _, _ in decoded)
    assert counts == {SCENE_TOPIC: scans * episodes, LOG_TOPIC: scans * episodes}
    assert {(t, s) for t, s, _ in decoded} == {
        (SCENE_TOPIC, "foxglove.SceneUpdate"),
        (LOG_TOPIC, "foxglove.Log"),
    }
    docs = _metrics(path)
    assert len(docs) == scans * episodes
    assert [d["scan"] for d in docs] == list(range(1, scans + 1)) * episodes
    # nothing went over a network: no counts, no latencies (a 0 was written for the counts)
    absent = ("messages", "bytes", "scan_latency_ms")
    assert all(k not in d for d in docs for k in absent)
    scenes = [dec for topic, _, dec in decoded if topic == SCENE_TOPIC]
    if name == "passive":
        doc = json.loads((out / "association.json").read_text())
        n_los = sum(len(rows) for rows in doc["measurements"])
        n_triples = len(doc["triples"])
        assert len(scenes[0].entities) == 5 + n_triples + 3 + n_los + 3 * n_triples
        assert {e.frame_id for e in scenes[0].entities} == {"world_km"}
        assert len(docs[0]["targets"]) == n_triples
    else:
        assert {len(s.entities) for s in scenes} == {entities}
        assert {e.frame_id for s in scenes for e in s.entities} == {"world_m"}
    # the replay's reader sees no message of a visual channel
    reader = RecordingReader(path)
    assert list(reader.samples()) == [] and reader.visual == 3 * scans * episodes


def test_paper_run_mcap_numbers_are_the_run_s(tmp_path):
    """``f``, ``tr P``, ``N_k``, NEES of the numbers channel == the run's own arrays."""
    kind, cfg = _paper(scans=5, allocation={"metrics": ["spectral"]})
    out = tmp_path / "run"
    kind.run(cfg, out, figures=False)
    from covnet.runs.visual import write_run_mcap

    docs = _metrics(write_run_mcap(kind, cfg, out))
    a = np.load(out / "arrays.npz")
    np.testing.assert_allclose([d["f"] for d in docs], a["value.spectral"])
    np.testing.assert_allclose([d["nees"] for d in docs], a["nees.spectral"])
    np.testing.assert_allclose(
        [d["trace_P"] for d in docs], np.trace(a["P_post.spectral"], axis1=1, axis2=2)
    )
    assert [d["n_active"] for d in docs] == list(a["enabled.spectral"].sum(axis=1))
    err = np.hypot(*(a["x_est.spectral"][:, [0, 2]] - a["truth"][:, [0, 2]]).T)
    np.testing.assert_allclose(
        [d["rmse"] for d in docs], np.sqrt(np.cumsum(err**2) / np.arange(1, 6))
    )


def test_layout_is_generated_and_names_real_topics_and_fields():
    import importlib.util
    import re

    from covnet.runs.visual import METRICS_SCHEMA, TOPICS

    path = ROOT / "docs" / "foxglove" / "make_layout.py"
    spec = importlib.util.spec_from_file_location("make_layout", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    committed = (ROOT / "docs" / "foxglove" / "covnet-layout.json").read_text()
    assert committed == module.text()  # regenerate: python docs/foxglove/make_layout.py
    topics = set(re.findall(r'"(/covnet/[a-z]+)', committed))
    assert topics == set(TOPICS)
    fields = re.findall(r'"/covnet/scan\.([A-Za-z_]+)"', committed)
    assert fields and set(fields) <= set(METRICS_SCHEMA["properties"])


def test_a_surveillance_scene_draws_track_states_and_cells():
    """The manager's tracks by state (a tentative one lighter, 1σ only, against the tentative
    P_d; a deleted one marked, with no ellipse) and the search cells shaded by u_c, decoded
    with the official protobuf reader; from the kind's view of a scan whose Status carries
    the cells."""
    import yaml as _yaml

    from covnet.covariance_control.config import from_dict
    from covnet.covariance_control.visual import Visual
    from covnet.runs.visual import ScanMessages

    data = _yaml.safe_load((ROOT / "configs" / "surveillance.yaml").read_text())
    sc = from_dict(data)
    u = np.linspace(0.0, 0.3, 16)
    st = msg.Status(scan=4, t=4.0, enabled=("P1",), trace_P=1.0, trace_Pd=2.0, value=3.0,
                    t_sent_ns=0, episode=0, fused=("P1",), cells=u)  # fmt: skip
    tracks = [
        msg.Track(scan=4, t=4.0, x=np.array([100.0 * i, 0, 5000, 0]), P=np.eye(4) * 100,
                  t_sent_ns=0, episode=0, target_id=f"K{i}", state=s)  # fmt: skip
        for i, s in ((1, "confirmed"), (2, "tentative"), (3, "deleted"))
    ]
    view = Visual(sc).view(ScanMessages(0, 4, st, None, None, {}, tracks))
    assert [e.state for e in view.estimates] == ["confirmed", "tentative", "deleted"]
    assert len(view.areas) == 16 and view.areas[-1].level == pytest.approx(1.0)
    update = _decode_bytes(SCENE_SCHEMA, scene_update(view, 4_000_000_000).encode())
    ents = {e.id: e for e in update.entities}
    assert {f"cell/C{c}" for c in range(16)} <= set(ents)
    alphas = [ents[f"cell/C{c}"].cubes[0].color.a for c in range(16)]
    assert alphas == sorted(alphas) and alphas[0] < alphas[-1]  # more mass, more shade
    assert len(ents["estimate/K1"].lines) == 3  # 1σ, 2σ and the desired ellipse
    assert len(ents["estimate/K2"].lines) == 2  # 1σ and the tentative desired ellipse
    c = ents["estimate/K2"].spheres[0].color
    assert (c.r, c.g, c.b, c.a) == pytest.approx(COLOURS["tentative"])
    assert ents["estimate/K3"].lines == [] and "deleted" in ents["estimate/K3"].texts[0].text


def test_run_mcap_times_are_scenario_time_episode_after_episode(tmp_path):
    """Episodes one after another, a second apart, each scan ``T`` after the last.  The Truth,
    which carries no episode, was taken for episode 0: from the second episode on the time base
    moved twice a scan (episode 1's scans 1, 2, 3 at 21, 28, 37 s; its scan 15 at 301 s)."""
    kind, cfg = _paper(scans=6)  # three metrics: three episodes
    out = tmp_path / "run"
    kind.run(cfg, out, figures=False)
    from covnet.runs.visual import write_run_mcap

    times = []
    with open(write_run_mcap(kind, cfg, out), "rb") as f:
        for _, _, m in make_reader(f).iter_messages(topics=[METRICS_TOPIC]):
            times.append(m.log_time / 1e9)
    T = float(cfg.period_s)
    episodes = len(cfg.allocation.metrics)
    assert len(times) == 6 * episodes
    expected, base = [], 0.0
    for _ in range(episodes):
        expected += [base + k * T for k in range(1, 7)]
        base = expected[-1] + 1.0
    np.testing.assert_allclose(times, expected)


def test_latency_only_from_senders_of_this_clock():
    """A measurement's one-way latency subtracts its sender's monotonic stamp from this
    process's clock: meaningful only when both read one clock (one boot and time namespace,
    ``node_kit.host_id``).  A sensor whose heartbeats name another host is left out (a sensors'
    host an hour younger gave -3 599 999 ms, hunt 11); one of this host, or not heard, counts."""
    from covnet.processes.node_kit import host_id

    kind, cfg = _paper(scans=3)
    vis = Visualiser(kind.visual(cfg), kind.episodes(cfg))
    for node, host in (("S1", host_id()), ("S2", "another-host")):
        hb = msg.Heartbeat(role="sensor", node_id=node, scan=0, t_sent_ns=0, host=host)
        assert vis.feed(hb.KIND, msg.heartbeat_key("r", "sensor", node), msg.encode(hb), 1) == []
    for sid, sent in (("S1", 1_000_000), ("S2", 3_600_001_000_000), ("S3", 1_000_000)):
        m = msg.Measurement(sensor_id=sid, scan=1, t=1.0, z=np.zeros((1, 2)), R=np.eye(2),
                            t_sent_ns=sent)  # fmt: skip (S2's clock an hour ahead)
        vis.feed(m.KIND, msg.measurement_key("r", sid), msg.encode(m), 3_000_000)
    status = msg.Status(scan=1, t=1.0, enabled=("S1", "S2", "S3"), trace_P=1.0, trace_Pd=1.0,
                        value=1.0, t_sent_ns=4_000_000)  # fmt: skip
    out = vis.feed(status.KIND, "k", msg.encode(status), 5_000_000)
    doc = json.loads(next(vm for vm in out if vm.topic == METRICS_TOPIC).data)
    assert doc["measurement_latency_ms"] == pytest.approx(2.0)  # S1's and S3's, not S2's
