"""The recorder's visual channels cut short by their time budget after a long run: it said so
only with ``--verbose`` (the launcher showed a node's line only for the manager, an error or a
traceback), so a 6 000-scan run's Foxglove view ended at scan 4 731 without a word.  The
recorder's line is a note, which the launcher shows."""

from __future__ import annotations

from collections import Counter

from covnet import kinds
from covnet.covariance_control.config import load
from covnet.processes.up import shown
from covnet.runs.recording import RecordingWriter
from covnet.runs.visual import Visualiser
from covnet.wire import messages as msg
from recorder.node import draw_recording


def test_a_visual_cut_is_a_note_the_launcher_shows(tmp_path, capsys, paper_path):
    cfg = load(paper_path)
    kind = kinds.of(cfg)
    w = RecordingWriter(tmp_path / "rec.mcap", run_id="r")
    cmd = msg.Command(1, 1.0, ("S1",), 5)
    w.write(msg.command_key("r", ("S1",)), msg.encode(cmd), 7, 5)
    w.flush()
    counts: Counter[str] = Counter()
    draw_recording(w, Visualiser(kind.visual(cfg), kind.episodes(cfg)), counts, budget_s=-1.0)
    w.close()
    assert counts["visual_cut"] == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert "visual channels" in line and "first 0 scans only" in line, line
    assert shown("recorder", line, verbose=False)
    assert not shown("recorder", "recorded 3 messages", verbose=False)
    assert shown("recorder", "recorded 3 messages", verbose=True)
    assert shown("S1", "Traceback (most recent call last):", verbose=False)
