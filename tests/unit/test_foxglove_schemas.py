"""Every JSON Schema covnet writes parses in Foxglove, and its JSON messages hold no null.

``jsonschema`` accepting the messages is not enough: Foxglove's own JSON-schema parser
(:mod:`foxglove_jsonschema`, its rules written out) rejects a whole channel for one field typed
``["number", "null"]``, and then plots nothing.  Checked here: the checker itself, the schemas
of the visual channels, the schemas the live view advertises to a real WebSocket client, and
the numbers messages of a scan that lacks values; and which WebSocket subprotocols the live
view accepts (what the README says of the viewers that can connect).  (Each kind's
``covnet run --mcap`` file is checked in ``test_visual.py``, the network recordings in the
integration tests.)"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import yaml
from foxglove_jsonschema import message_problems, schema_problems
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from covnet import kinds
from covnet.processes.up import free_port
from covnet.runs.live import LiveView
from covnet.runs.visual import ENCODINGS, METRICS_TOPIC, SCHEMAS, TOPICS, Visualiser
from covnet.wire import messages as msg

ROOT = Path(__file__).resolve().parents[2]

NUM = {"type": "number"}


def _obj(**props):
    return {"type": "object", "properties": props}


# ---- the checker: what Foxglove's parser rejects --------------------------------------------

REJECTED = {
    "type list with null": _obj(f={"type": ["number", "null"]}),
    "null type": _obj(f={"type": "null"}),
    "no type": _obj(f={"description": "x"}),
    "oneOf": _obj(f={"oneOf": [NUM, {"type": "null"}]}),
    "anyOf": _obj(f={"anyOf": [NUM, {"type": "string"}]}),
    "unknown type": _obj(f={"type": "float"}),
    "nested object's field": _obj(o=_obj(g={"type": ["integer", "null"]})),
    "object without properties": _obj(o={"type": "object"}),
    "array item type list": _obj(a={"type": "array", "items": {"type": ["number", "null"]}}),
    "array of arrays": _obj(a={"type": "array", "items": {"type": "array", "items": NUM}}),
    "array of objects' field": _obj(a={"type": "array", "items": _obj(x={"type": "null"})}),
    "array without items": _obj(a={"type": "array"}),
    "string encoding": _obj(s={"type": "string", "contentEncoding": "base16"}),
    "root not an object": {"type": "array", "items": NUM},
}


@pytest.mark.parametrize("name", sorted(REJECTED))
def test_checker_rejects_what_foxglove_rejects(name):
    assert schema_problems(REJECTED[name])


def test_checker_accepts_what_foxglove_parses():
    ok = _obj(
        b={"type": "boolean"}, s={"type": "string"}, n=NUM, i={"type": "integer"},
        raw={"type": "string", "contentEncoding": "base64"},
        o=_obj(x=NUM), a={"type": "array", "items": _obj(id={"type": "string"}, v=NUM)},
        xs={"type": "array", "items": NUM},
    )  # fmt: skip
    assert schema_problems(ok) == []
    assert message_problems(b'{"a":1,"t":[{"id":"T1","v":2.5}]}') == []
    assert message_problems(b'{"a":null}') == ["a: null"]
    assert message_problems(b'{"t":[{"v":null}]}') == ["t[0].v: null"]
    assert message_problems(b'{"a":NaN}')  # JSON.parse has no NaN


# ---- covnet's schemas -------------------------------------------------------------------------


def _json_topics():
    topics = [t for t in TOPICS if SCHEMAS[t].encoding == "jsonschema"]
    assert topics == [METRICS_TOPIC]  # a new JSON channel is checked here too
    return topics


@pytest.mark.parametrize("topic", [METRICS_TOPIC])
def test_visual_json_schemas_parse_in_foxglove(topic):
    assert topic in _json_topics() and ENCODINGS[topic] == "json"
    assert schema_problems(json.loads(SCHEMAS[topic].data)) == []


async def _advertised(port: int, timeout: float = 10.0) -> dict[str, dict]:
    """The channels the live view advertises to a client speaking ``foxglove.sdk.v1``."""
    channels: dict[str, dict] = {}
    async with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]) as ws:
        assert ws.subprotocol == "foxglove.sdk.v1"
        while not set(TOPICS) <= set(channels):
            m = json.loads(await asyncio.wait_for(ws.recv(), timeout))
            if m["op"] == "advertise":
                channels |= {c["topic"]: c for c in m["channels"]}
    return channels


def test_live_view_advertises_schemas_foxglove_parses():
    live = LiveView("127.0.0.1", free_port())
    try:
        channels = asyncio.run(_advertised(live.port))
    finally:
        live.close()
    json_channels = [c for c in channels.values() if c["encoding"] == "json"]
    assert [c["topic"] for c in json_channels] == _json_topics()
    for c in json_channels:
        assert c["schemaEncoding"] == "jsonschema"
        assert schema_problems(json.loads(c["schema"])) == [], c["topic"]


async def _subprotocol(port: int, offered: list[str]) -> str | int:
    """The subprotocol the live view picks among ``offered``, or the HTTP status refusing it."""
    try:
        async with connect(f"ws://127.0.0.1:{port}", subprotocols=offered) as ws:
            return str(ws.subprotocol)
    except InvalidStatus as exc:
        return exc.response.status_code


def test_live_view_speaks_only_the_sdk_subprotocols():
    """The SDK's server accepts ``foxglove.sdk.v1`` (and ``foxglove.sdk.v1.1``, preferred) and
    refuses the older ``foxglove.websocket.v1``: a viewer offering only that cannot connect."""
    live = LiveView("127.0.0.1", free_port())
    try:
        got = {
            name: asyncio.run(_subprotocol(live.port, offered))
            for name, offered in {
                "sdk.v1": ["foxglove.sdk.v1"],
                "both sdk": ["foxglove.sdk.v1", "foxglove.sdk.v1.1"],
                "old and sdk.v1": ["foxglove.websocket.v1", "foxglove.sdk.v1"],
                "old only": ["foxglove.websocket.v1"],
            }.items()
        }
    finally:
        live.close()
    assert got == {
        "sdk.v1": "foxglove.sdk.v1",
        "both sdk": "foxglove.sdk.v1.1",
        "old and sdk.v1": "foxglove.sdk.v1",
        "old only": 400,
    }


# ---- the messages: a value not known is left out ----------------------------------------------


def test_numbers_leave_out_what_is_not_known():
    """A scan with no command, truth or track: RMSE, NEES and the latencies are not known, and
    a track without its truth has no error, RMSE or NEES: they are left out, never null."""
    data = yaml.safe_load((ROOT / "configs" / "paper.yaml").read_text())
    kind, cfg = kinds.from_dict({**data, "scans": 3}, "paper")
    vis = Visualiser(kind.visual(cfg), kind.episodes(cfg))
    status = msg.Status(scan=1, t=1.0, enabled=(), trace_P=1.0, trace_Pd=2.0, value=0.5,
                        t_sent_ns=4_000_000)  # fmt: skip
    (vm,) = [v for v in vis.feed(status.KIND, "k", msg.encode(status), 5_000_000)
             if v.topic == METRICS_TOPIC]  # fmt: skip
    assert message_problems(vm.data) == []
    doc = json.loads(vm.data)
    jsonschema.validate(doc, json.loads(vm.schema.data))
    gone = {"rmse", "nees", "scan_latency_ms", "measurement_latency_ms",
            "measurement_latency_max_ms"}  # fmt: skip
    assert not gone & set(doc)
    assert doc["targets"] == [] and doc["n_active"] == 0 and doc["f"] == 0.5

    # and with a track but no truth: the target's error, RMSE and NEES are left out
    x, P = np.array([1.0, 0.0, 2.0, 0.0]), np.eye(4)
    track = msg.Track(scan=2, t=2.0, x=x, P=P, t_sent_ns=1)
    status = msg.Status(scan=2, t=2.0, enabled=("S1",), trace_P=4.0, trace_Pd=2.0, value=0.5,
                        t_sent_ns=2)  # fmt: skip
    out = []
    for m in (track, status):
        out += vis.feed(m.KIND, "k", msg.encode(m), 3)
    (vm,) = [v for v in out if v.topic == METRICS_TOPIC]
    assert message_problems(vm.data) == []
    (target,) = json.loads(vm.data)["targets"]
    assert target["trace_P"] == pytest.approx(4.0)
    assert not {"error", "rmse", "nees"} & set(target)
