"""Start-up: what a process imports is what it needs.  ``scipy.linalg``'s package import costs a
process a few tenths of a second; the core's LAPACK routines come without it
(:mod:`covnet.core.lapack`), and the node processes that never factor a matrix, the world, a
measuring sensor and the recorder, never load even those.  Checked in fresh interpreters (a
structure test, not a timing one: the timing is ``python -X importtime``'s)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "configs" / "paper.yaml"


def _modules_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", code + "\nimport sys, json; print(json.dumps(sorted(sys.modules)))"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def test_the_core_lapack_routines_are_scipys_own():
    from covnet.core.lapack import flapack

    fast = flapack()
    from scipy.linalg import lapack  # imported after: it reuses the same extension module

    for name in ("dpotrf", "dpotrs", "dpotri", "dsyev", "dtrtri"):
        assert getattr(fast, name) is getattr(lapack, name)
    A = np.array([[4.0, 1.0], [1.0, 3.0]])
    c1, i1 = fast.dpotrf(A, lower=1)
    c2, i2 = lapack.dpotrf(A, lower=1)
    assert i1 == i2 == 0 and c1.tobytes() == c2.tobytes()


def test_covnet_run_does_not_import_scipy_linalg(tmp_path):
    mods = _modules_after(
        "from covnet.cli.app import main\n"
        f"main(['run', {str(PAPER)!r}, '--no-figures', '--out', {str(tmp_path / 'r')!r},"
        " '--metric', 'spectral'])"
    )
    assert "scipy.linalg._flapack" in mods
    assert "scipy.linalg" not in mods
    # nor what only other commands or modes use: the batch machinery (mc, compare, sweep),
    # the slow-link simulation, numpy.ma (numpy.median's import), the message schemas
    for mod in (
        "covnet.wire.messages",
        "msgpack",
        "covnet.batches.pool",
        "covnet.batches.trials",
        "multiprocessing",
        "covnet.covariance_control.latency_sim",
        "covnet.covariance_control.batch_commands",
        "numpy.ma",
        # nor a validation library (covnet.records validates), nor what one pulled in
        "pydantic",
        "asyncio",
        "ssl",
    ):
        assert mod not in mods, mod


def test_the_world_a_sensor_and_the_recorder_need_no_lapack():
    mods = _modules_after(
        "from covnet import kinds\n"
        "import sensors.covariance, world.covariance, recorder.node, covnet.runs.recording\n"
        "from covnet.covariance_control.model import build_model, truth_trajectory\n"
        f"kind, cfg = kinds.load({str(PAPER)!r})\n"
        "truth_trajectory(build_model(cfg))"
    )
    assert not {m for m in mods if m.startswith("scipy.linalg")}, sorted(
        m for m in mods if m.startswith("scipy")
    )


def test_the_local_batch_path_imports_no_dask(tmp_path):
    """Issue 18: ``--cluster`` is the only way into dask; a sweep on the local pool (and the
    batch layer, the API) never imports it."""
    import yaml

    data = yaml.safe_load((REPO / "configs" / "latency.yaml").read_text())
    data["scans"] = 12
    data["sweep"] = {"delay_ms": [0, 200], "loss": [0.0], "modes": ["central"],
                     "account_for_loss": [False], "seeds": 2}  # fmt: skip
    cfg = tmp_path / "s.yaml"
    cfg.write_text(yaml.safe_dump(data))
    mods = _modules_after(
        "import covnet.cli.api, covnet.batches.trials\n"
        "from covnet.cli.app import main\n"
        f"assert main(['sweep', {str(cfg)!r}, '--no-figures', '--workers', '2', '--out', "
        f"{str(tmp_path / 'o')!r}]) == 0"
    )
    assert "covnet.batches.trials" in mods
    assert not {m for m in mods if m.split(".")[0] in ("dask", "distributed")}, sorted(
        m for m in mods if m.startswith(("dask", "distributed"))
    )
    assert "covnet.batches.cluster" not in mods
