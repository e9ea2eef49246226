"""The three runs a README recipe must survive, for a config naming a newly registered entry:
``covnet run`` (the CLI, in process), a lockstep network run (world, sensors, recorder and
manager loops as threads over one InMemoryHub, :func:`nodethreads.run_recorded_network`) and
``covnet replay`` of that network run (the CLI, in process).  The entry is registered by the
test (``monkeypatch.setitem``) in this process, where all three run."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml
from nodethreads import run_recorded_network

from covnet.cli.app import main
from covnet.covariance_control.config import load
from covnet.runs.rundir import load_arrays

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "configs" / "paper.yaml"


def write_config(tmp_path: Path, allocation: dict[str, Any], scans: int = 20) -> Path:
    """The paper scenario, shortened, recorded, with ``allocation`` merged in."""
    data = yaml.safe_load(PAPER.read_text())
    data["scans"] = scans
    data.setdefault("allocation", {}).update(allocation)
    data.setdefault("network", {})["record"] = True
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def run_all_three(cfg: Path, tmp_path: Path, metric: str) -> None:
    """(a) ``covnet run``, (b) the lockstep network run, equal to (a) bit for bit, and (c)
    ``covnet replay`` of (b), which reproduces its summary byte for byte."""
    run_dir = tmp_path / "run"
    assert main(["run", str(cfg), "--no-figures", "--out", str(run_dir)]) == 0
    sc = load(cfg)
    net_dir = tmp_path / "net"
    result, _ = run_recorded_network(sc, [metric], net_dir)
    assert result.completed and result.error is None
    a, b = load_arrays(run_dir / "arrays.npz"), load_arrays(net_dir / "arrays.npz")
    assert f"enabled.{metric}" in a and sorted(a) == sorted(b)
    for key in a:  # every array of the run: decisions, values, estimates, covariances
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert main(["replay", str(net_dir)]) == 0
    replayed = (net_dir / "replay" / "summary.json").read_bytes()
    assert replayed == (net_dir / "summary.json").read_bytes()
