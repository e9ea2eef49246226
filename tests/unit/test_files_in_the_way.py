"""Files that are not what covnet expects in their place (found by a hunt through damaged run
directories): a FIFO or a device read as a config or a table hung or read until the machine's
memory ran out; a directory where covnet writes a trial ended in an IsADirectoryError
traceback.  Each is now named: a config or table that is not a regular file is refused, and
an OS error on a file covnet reads or writes ends the command with the file and the reason
(exit 1), never a traceback."""

from __future__ import annotations

import os
import shutil

import pytest

from covnet.cli.app import main
from covnet.config import ConfigError, read_yaml
from covnet.runs.rundir import read_json
from tests.conftest import REPO


def test_a_fifo_as_a_config_or_a_table_is_refused_not_read(tmp_path):
    fifo = tmp_path / "config.json"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match="not a regular file"):
        read_yaml(fifo)
    with pytest.raises(ValueError, match="not a regular file"):
        read_json(fifo)
    dev = tmp_path / "zero.yaml"
    dev.symlink_to("/dev/zero")
    with pytest.raises(ConfigError, match="not a regular file"):
        read_yaml(dev)


def test_a_directory_where_a_trial_is_written_ends_the_batch_with_its_name(tmp_path, capsys):
    out = tmp_path / "mc"
    args = ["mc", str(REPO / "configs" / "paper.yaml"), "--seeds", "2", "--workers", "1"]
    assert main([*args, "--out", str(out)]) == 0
    trials = sorted((out / "trials").rglob("*.json"))
    trials[0].unlink()
    trials[0].mkdir()
    capsys.readouterr()
    assert main([*args, "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert str(trials[0]) in err and "Traceback" not in err
    shutil.rmtree(out)


@pytest.mark.parametrize("make", [os.mkfifo, os.mkdir])
def test_a_recording_segment_that_is_not_a_file_stops_the_reading_with_a_note(tmp_path, make):
    """``recording.2.mcap`` a FIFO hung ``covnet replay``; a directory ended in a traceback."""
    from covnet.runs.recording import RecordingReader, RecordingWriter

    path = tmp_path / "recording.mcap"
    RecordingWriter(path, run_id="r").close()
    make(tmp_path / "recording.2.mcap")
    reader = RecordingReader(path)
    assert list(reader.samples()) == []
    assert reader.error == "recording.2.mcap is not a regular file"


def test_plot_of_a_batch_directory_without_its_table_says_so(tmp_path, capsys):
    """It said "not a complete run directory (missing summary.json, arrays.npz)"."""
    out = tmp_path / "mc"
    args = ["mc", str(REPO / "configs" / "paper.yaml"), "--seeds", "2", "--workers", "1"]
    assert main([*args, "--out", str(out)]) == 0
    (out / "montecarlo.json").unlink()
    capsys.readouterr()
    assert main(["plot", str(out)]) == 2
    err = capsys.readouterr().err
    assert "without its table" in err and "summary.json" not in err
