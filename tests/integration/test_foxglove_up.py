"""``covnet up --foxglove``: a real Foxglove WebSocket client (``websockets``, offering the
protocol's subprotocols as the Foxglove app does) subscribes to the scene and the numbers while
a real network runs, and receives the run's scans; the recording's visual channels decode with
the official readers and agree with ``covnet run --mcap`` of the same lockstep run."""

from __future__ import annotations

import asyncio
import base64
import json
import struct
from collections import Counter

import jsonschema
import pytest
import yaml
from foxglove_jsonschema import message_problems, schema_problems
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory
from multiproc import REPO, CovnetProcess, assert_nothing_left
from websockets.asyncio.client import connect

from covnet.cli.app import main as covnet_main
from covnet.processes.up import free_port

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

SCENE, SCAN, LOG = "/covnet/scene", "/covnet/scan", "/covnet/log"
#: what a Foxglove client offers: the SDK's server (0.30) speaks the protocol as
#: ``foxglove.sdk.v1``, the older servers as ``foxglove.websocket.v1``
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


def _visual(path):
    """``topic -> [decoded]`` of a file's visual channels (protobuf: mcap-protobuf-support;
    JSON: validated against the file's JSON Schema, which Foxglove's parser accepts; no null)."""
    out: dict[str, list] = {SCENE: [], SCAN: [], LOG: []}
    with open(path, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, ch, _, dec in r.iter_decoded_messages(topics=[SCENE, LOG]):
            out[ch.topic].append(dec)
        f.seek(0)
        for schema, _, m in make_reader(f).iter_messages(topics=[SCAN]):
            assert schema_problems(json.loads(schema.data)) == []
            assert message_problems(m.data) == []
            doc = json.loads(m.data)
            jsonschema.validate(doc, json.loads(schema.data))
            out[SCAN].append(doc)
    return out


async def _watch(url: str, until_scans: int, timeout: float):
    """Follow the protocol: serverInfo, advertise, subscribe to the scene and the numbers,
    then decode each binary MESSAGE_DATA (opcode 1, subscription id, log time, payload)."""
    scenes, scans = [], []
    async with connect(url, subprotocols=SUBPROTOCOLS, max_size=None) as ws:
        assert ws.subprotocol in SUBPROTOCOLS
        channels: dict[str, dict] = {}
        while not {SCENE, SCAN} <= set(channels):
            m = json.loads(await asyncio.wait_for(ws.recv(), timeout))
            if m["op"] == "advertise":
                channels |= {c["topic"]: c for c in m["channels"]}
        assert channels[SCENE]["schemaName"] == "foxglove.SceneUpdate"
        assert channels[SCENE]["encoding"] == "protobuf"
        assert channels[SCAN]["encoding"] == "json"
        assert schema_problems(json.loads(channels[SCAN]["schema"])) == []
        raw = base64.b64decode(channels[SCENE]["schema"])
        schema = Schema(id=1, name="foxglove.SceneUpdate", encoding="protobuf", data=raw)
        decode = DecoderFactory().decoder_for("protobuf", schema)
        subs = [{"id": 1, "channelId": channels[SCENE]["id"]},
                {"id": 2, "channelId": channels[SCAN]["id"]}]  # fmt: skip
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while len(scans) < until_scans and loop.time() < deadline:
            try:
                data = await asyncio.wait_for(ws.recv(), deadline - loop.time())
            except TimeoutError:
                break
            if isinstance(data, str):
                continue
            op, sub, _log_time = struct.unpack_from("<BIQ", data)
            assert op == 1
            payload = data[13:]
            if sub == 1:
                scenes.append(decode(payload))
            else:
                assert message_problems(payload) == []
                scans.append(json.loads(payload))
    return scenes, scans


def test_live_client_receives_scene_updates(tmp_path):
    data = yaml.safe_load((REPO / "configs" / "paper.yaml").read_text())
    data["scans"] = 60
    cfg = tmp_path / "paper.yaml"
    cfg.write_text(yaml.safe_dump(data))
    port = free_port()
    out = tmp_path / "up"
    address = f"127.0.0.1:{port}"
    p = CovnetProcess(["up", str(cfg), "--out", str(out), "--metric", "spectral", "--realtime",
                       "--speed", "20", "--foxglove", address, "--no-figures"])  # fmt: skip
    try:
        assert p.wait_for("READY", timeout=60) is not None, p.output()
        scenes, scans = asyncio.run(_watch(f"ws://127.0.0.1:{port}", until_scans=20, timeout=30))
        assert p.wait(timeout=60) == 0, p.output()
    finally:
        p.stop()
    assert_nothing_left(out)
    assert len(scans) >= 20 and len(scenes) >= 20, (len(scans), len(scenes))
    ks = [d["scan"] for d in scans]
    assert ks == sorted(ks) and len(set(ks)) == len(ks)  # the run's scans, in order
    assert all(1 <= k <= 60 for k in ks)
    for s in scenes:
        ids = {e.id for e in s.entities}
        assert {"truth/T1", "estimate/T1"} <= ids and sum(i.startswith("sensor/") for i in ids) == 8
    # the recording has every scan's visual messages, and the replay still reproduces the run
    rec = _visual(out / "recording.mcap")
    assert [len(rec[t]) for t in (SCENE, SCAN, LOG)] == [60, 60, 60]
    assert [d["scan"] for d in rec[SCAN]] == list(range(1, 61))
    assert all(d["messages"] > 0 and "scan_latency_ms" in d for d in rec[SCAN])
    assert covnet_main(["replay", str(out)]) == 0


def _comparable(doc: dict) -> dict:
    drop = {"messages", "bytes", "scan_latency_ms", "measurement_latency_ms",
            "measurement_latency_max_ms"}  # fmt: skip
    return {k: v for k, v in doc.items() if k not in drop}


def _entities(scene) -> dict:
    """A scene's entities without their times (the network's are receive times)."""
    out = {}
    for e in scene.entities:
        e.ClearField("timestamp")
        out[e.id] = e.SerializeToString(deterministic=True)
    return out


def test_lockstep_recording_agrees_with_run_mcap(tmp_path):
    """A lockstep network run draws exactly what ``covnet run --mcap`` draws of the same
    scenario: the same scenes, the same numbers (bar the network's counts and latencies)."""
    data = yaml.safe_load((REPO / "configs" / "paper.yaml").read_text())
    data["scans"] = 40
    cfg = tmp_path / "paper.yaml"
    cfg.write_text(yaml.safe_dump(data))
    up, run = tmp_path / "up", tmp_path / "run"
    p = CovnetProcess(["up", str(cfg), "--out", str(up), "--no-figures"])
    try:
        assert p.wait(timeout=90) == 0, p.output()
    finally:
        p.stop()
    assert covnet_main(["run", str(cfg), "--out", str(run), "--no-figures", "--mcap"]) == 0
    a, b = _visual(up / "recording.mcap"), _visual(run / "run.mcap")
    assert Counter({t: len(v) for t, v in a.items()}) == {SCENE: 120, SCAN: 120, LOG: 120}
    assert [_comparable(d) for d in a[SCAN]] == [_comparable(d) for d in b[SCAN]]
    assert [_entities(s) for s in a[SCENE]] == [_entities(s) for s in b[SCENE]]
    assert [m.message for m in a[LOG]] == [m.message for m in b[LOG]]
