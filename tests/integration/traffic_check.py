"""``covnet compare``'s messages and bytes per scan against what a network run's nodes sent:
the recording holds every message, and its payload lengths are the bytes on the wire.

``compare`` (and ``compare --policies``) count them by encoding the messages of the run's
decisions (:func:`covnet.covariance_control.compare.traffic_per_scan`,
:func:`~covnet.covariance_control.compare_policies.targets_traffic_per_scan`); their fields
were placeholders that encode shorter than real ones (``t_sent_ns = 1``, no ``seq``: 7 % short
of a recording).  These checks hold the estimate to the recording of the same decisions,
message for message and byte for byte."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np

from covnet import kinds
from covnet.covariance_control import targets
from covnet.covariance_control.compare import traffic_per_scan
from covnet.covariance_control.compare_policies import targets_traffic_per_scan
from covnet.covariance_control.replay import RECORDING
from covnet.runs.recording import read_recording
from covnet.runs.rundir import load_arrays
from covnet.wire import messages as msg

#: what the comparison counts: a scan's tasking, reports and results (truth, heartbeats and
#: the live view are not the structure's traffic)
COUNTED = (msg.Command, msg.Measurement, msg.LocalTrack, msg.Track, msg.Status)


def sent_per_episode(out: Path) -> dict[int, tuple[int, int]]:
    """Per episode: (messages, bytes) of the counted kinds in ``out``'s recording."""
    n: Counter[int] = Counter()
    size: Counter[int] = Counter()
    for s in read_recording(out / RECORDING):
        m = msg.decode(s.payload)
        if isinstance(m, COUNTED):
            n[m.episode] += 1
            size[m.episode] += len(s.payload)
    return {e: (n[e], size[e]) for e in n}


def assert_compare_counts_what_was_sent(out: Path, mode: str, graph: str | None = None) -> None:
    """The estimate for the first episode's decisions (``arrays.npz``) is the recording's count:
    ``mode`` as ``covnet compare --modes`` names it (``central``, ``info``, ``peer-info``, ...);
    a ``targets:`` config by the many-target count (``info``: local tracks)."""
    _, sc = kinds.from_dict(json.loads((out / "config.json").read_text()), "config.json")
    arrays = load_arrays(out / "arrays.npz")
    metrics = [str(m) for m in arrays["metrics"]]
    sent = sent_per_episode(out)
    assert sorted(sent) == list(range(len(metrics))), sorted(sent)
    # the first episode: a sensor numbers its messages over the whole run (``seq``), and a
    # compare trial is one metric's run, numbered from 1 as the first episode is
    for e, metric in enumerate(metrics[:1]):
        if sc.multitarget:
            assignment = arrays[f"assignment.{metric}"]
            est = targets_traffic_per_scan(
                targets.build(sc), assignment, arrays[f"returns.{metric}"], mode == "info"
            )
            K = len(assignment)
        else:
            first = f"enabled.{metric}.{sc.sensor_ids[0]}"  # peer: the first node's decisions
            enabled = arrays[first] if first in arrays else arrays[f"enabled.{metric}"]
            est = traffic_per_scan(sc, mode, np.asarray(enabled, dtype=bool), graph)
            K = len(enabled)
        messages, size = sent[e]
        assert est["messages_per_scan"] == messages / K, (metric, est, messages / K)
        assert est["bytes_per_scan"] == size / K, (metric, est, size / K)
