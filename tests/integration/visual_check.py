"""What every network recording's visual channels must hold (:mod:`covnet.runs.visual`): one scene,
one numbers message and one log line per scan, decoded with the official readers."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import jsonschema
from foxglove_jsonschema import message_problems, schema_problems
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

TOPICS = ("/covnet/scene", "/covnet/scan", "/covnet/log")


def assert_visual_channels(recording: Path, scans: list[int], frame: str) -> list[dict]:
    """Every visual message of ``recording`` decodes (protobuf: mcap-protobuf-support; JSON:
    its JSON Schema, which Foxglove's parser accepts, and no null in a message); one of each
    per scan of ``scans``, in order; scenes in ``frame``.
    Returns the numbers."""
    counts: Counter[str] = Counter()
    docs = []
    with open(recording, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, ch, _, dec in r.iter_decoded_messages(topics=[TOPICS[0], TOPICS[2]]):
            counts[ch.topic] += 1
            if ch.topic == TOPICS[0]:
                assert schema.name == "foxglove.SceneUpdate"
                assert {e.frame_id for e in dec.entities} == {frame}
        f.seek(0)
        for schema, _, m in make_reader(f).iter_messages(topics=[TOPICS[1]]):
            assert schema_problems(json.loads(schema.data)) == []
            assert message_problems(m.data) == []
            doc = json.loads(m.data)
            jsonschema.validate(doc, json.loads(schema.data))
            docs.append(doc)
    assert counts == {TOPICS[0]: len(scans), TOPICS[2]: len(scans)}
    assert [d["scan"] for d in docs] == scans
    return docs
