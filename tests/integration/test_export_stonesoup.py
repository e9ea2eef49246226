"""``covnet export RUN --format stonesoup`` (issue 27, Stone Soup interop), with Stone Soup
installed: the exported ``GroundTruthPath`` s and ``Track`` s read back from Stone Soup's YAML
are the run's arrays, and Stone Soup's own OSPA and GOSPA metric generators on them give
covnet's per-scan OSPA and GOSPA.

How covnet computes them (``covnet.covariance_control.results.ospa_series``,
``covnet.core.ospa``): per scan, the set of true positions ``(x, y)`` against the set of
estimated positions, Euclidean distance, cut-off ``c`` and order ``p`` from the config's
``ospa`` (``cutoff_m``, ``order``), GOSPA with ``α = 2``, assignments minimising
``Σ min(d, c)^p``.  Stone Soup is configured identically: ``OSPAMetric`` / ``GOSPAMetric``
with the same ``c`` and ``p``, ``measure = Euclidean(mapping=(0, 2))`` (the positions of the
state ``[x, vx, y, vy]``), GOSPA's ``α`` fixed at 2 and no switching penalty (its default 0).

Tolerance: ``rtol = 1e-9``; the two sum the same terms in a different order, so they differ
by a few ulps (about 1e-16 relative here).  One difference is not rounding: Stone Soup
1.9.1's ``OSPAMetric`` picks its assignment by minimising ``Σ min(d, c)`` (the distances, not
their ``p``-th powers) and then sums ``min(d, c)^p``; for ``p ≠ 1`` that can be a worse
assignment than OSPA's definition asks for, so its value can exceed the true OSPA when
targets are closer together than their errors (the last test here).  In these runs the
targets are kilometres apart and the two agree; GOSPA's assignment is on ``min(d, c)^p`` in
both.
"""

from __future__ import annotations

import json
import subprocess
import sys
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
import yaml

from covnet.core.ospa import gospa, ospa
from covnet.runs import export as ex
from covnet.runs.rundir import load_arrays

stonesoup = pytest.importorskip("stonesoup")

from stonesoup.measures import Euclidean  # noqa: E402
from stonesoup.metricgenerator.manager import MultiManager  # noqa: E402
from stonesoup.metricgenerator.ospametric import GOSPAMetric, OSPAMetric  # noqa: E402
from stonesoup.serialise import YAML  # noqa: E402
from stonesoup.types.state import GaussianState, State  # noqa: E402

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

ROOT = Path(__file__).resolve().parents[2]
RTOL = 1e-9


def _config(tmp_path: Path, name: str, scans: int, **changes) -> Path:
    """``configs/<name>.yaml`` shortened to ``scans`` (a many-target config's turn and
    priority change moved inside them)."""
    data = yaml.safe_load((ROOT / "configs" / f"{name}.yaml").read_text())
    data["scans"] = scans
    for key, value in changes.items():  # a dict changes those keys of the section
        data[key] = {**data[key], **value} if isinstance(value, dict) else value
    for t in data.get("targets", []) if name == "multitarget" else []:
        for m in t.get("manoeuvres", []):
            m.update(from_scan=2, to_scan=scans - 1)
        for d in t["desired"][1:]:
            d["from_scan"] = scans // 2
    p = tmp_path / f"{name}-short.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _covnet(*args: str, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    r = subprocess.run(
        [sys.executable, "-m", "covnet", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    return r


def _export(run: Path, tmp_path: Path) -> dict:
    """``covnet export RUN --format stonesoup`` read back with Stone Soup's own YAML."""
    out = tmp_path / f"{run.name}.yaml"
    r = _covnet("export", str(run), "--format", "stonesoup", "--out", str(out))
    assert r.stdout.strip() == str(out)
    doc = YAML().load(out.read_text())
    return {str(k): v for k, v in doc.items()}


def _run_exported(tmp_path: Path, name: str, scans: int, **changes) -> tuple:
    """``covnet run`` of the shortened config, its export read back and checked state by state
    (:func:`_check_states`): ``(run directory, export, arrays, summary)``."""
    cfg = _config(tmp_path, name, scans, **changes)
    run = tmp_path / name
    _covnet("run", str(cfg), "--out", str(run), "--no-figures")
    doc = _export(run, tmp_path)
    _check_states(doc, run)
    return run, doc, load_arrays(run / "arrays.npz"), json.loads((run / "summary.json").read_text())


def _stone_soup_metrics(truths, tracks, c: float, p: float) -> tuple[np.ndarray, np.ndarray]:
    """Stone Soup's per-timestamp OSPA and GOSPA distances on positions."""
    measure = Euclidean(mapping=(0, 2))
    manager = MultiManager(
        [OSPAMetric(c=c, p=p, measure=measure), GOSPAMetric(c=c, p=p, measure=measure)]
    )
    manager.add_data({"groundtruth_paths": truths, "tracks": tracks})
    metrics = manager.generate_metrics()
    o = metrics["ospa_generator"]["OSPA distances"].value
    g = metrics["gospa_generator"]["GOSPA Metrics"].value
    assert [m.timestamp for m in o] == [m.timestamp for m in g]
    return np.array([m.value for m in o]), np.array([m.value["distance"] for m in g])


def _check_states(doc: dict, run: Path) -> None:
    """Every exported state is the run's array, bit for bit, at ``EPOCH + t``."""
    for e in ex.read_run(run):
        got = doc[e.name]
        assert {t.id for t in got["groundtruth_paths"]} == {s.id for s in e.truths}
        assert {t.id for t in got["tracks"]} == {s.id for s in e.tracks}
        paths = {p.id: p for p in got["groundtruth_paths"]}
        tracks = {t.id: t for t in got["tracks"]}
        for s in e.truths:
            states = paths[s.id].states
            assert np.array_equal([x.state_vector.ravel() for x in states], s.x)
            assert [x.timestamp for x in states] == [
                ex.EPOCH + timedelta(seconds=float(t)) for t in s.t
            ]
        for s in e.tracks:
            states = tracks[s.id].states
            assert all(isinstance(x, GaussianState) for x in states)
            assert np.array_equal([x.state_vector.ravel() for x in states], s.x)
            assert np.array_equal([x.covar for x in states], s.P)


def _check_against_covnet(doc: dict, run: Path) -> int:
    """Stone Soup's OSPA / GOSPA on the export == covnet's per-scan values (arrays.npz and
    summary.json) for every metric; returns the number of scans compared."""
    a = load_arrays(run / "arrays.npz")
    summary = json.loads((run / "summary.json").read_text())
    c, p = summary["ospa"]["cutoff_m"], summary["ospa"]["order"]
    n = 0
    for m in (str(x) for x in a["metrics"]):
        o, g = _stone_soup_metrics(doc[m]["groundtruth_paths"], doc[m]["tracks"], c, p)
        assert o.shape == a[f"ospa.{m}"].shape
        np.testing.assert_allclose(o, a[f"ospa.{m}"], rtol=RTOL, atol=0)
        np.testing.assert_allclose(g, a[f"gospa.{m}"], rtol=RTOL, atol=0)
        np.testing.assert_allclose(o, summary["metrics"][m]["ospa"], rtol=RTOL, atol=0)
        np.testing.assert_allclose(g, summary["metrics"][m]["gospa"], rtol=RTOL, atol=0)
        n += o.size
    return n


def test_many_targets_stone_soup_ospa_and_gospa_are_covnets(tmp_path):
    cfg = _config(tmp_path, "multitarget", 8)
    run = tmp_path / "mt"
    _covnet("run", str(cfg), "--out", str(run), "--no-figures")
    doc = _export(run, tmp_path)
    assert sorted(doc) == ["abs_trace", "spectral"]
    _check_states(doc, run)
    assert _check_against_covnet(doc, run) == 2 * 8
    # the Python entry point gives the same objects (one episode)
    truths, tracks = ex.to_stonesoup(run, "abs_trace")
    o, g = _stone_soup_metrics(truths, tracks, 200.0, 2.0)
    np.testing.assert_allclose(o, load_arrays(run / "arrays.npz")["ospa.abs_trace"], rtol=RTOL)


def test_two_exports_of_a_run_are_the_same_file(tmp_path):
    """The sets' items are written by id: Stone Soup's objects hash by their address, so the
    tracks and paths came in another order at each export (T1, T3, T2 then T3, T2, T1; hunt
    14).  Two processes and this one write the same bytes, which Stone Soup still reads."""
    cfg = _config(tmp_path, "multitarget", 4)
    run = tmp_path / "mt"
    _covnet("run", str(cfg), "--out", str(run), "--no-figures")
    files = [tmp_path / f"export-{i}.yaml" for i in range(3)]
    for f in files[:2]:
        _covnet("export", str(run), "--format", "stonesoup", "--out", str(f))
    ex.export(run, "stonesoup", files[2])
    texts = [f.read_bytes() for f in files]
    assert texts[0] == texts[1] == texts[2]
    ids = [line.split(":")[1].strip() for line in texts[0].decode().splitlines()
           if line.startswith("    - id:")]  # fmt: skip
    assert ids == ["T1", "T2", "T3"] * 4, ids  # (2 episodes x truths, tracks)
    doc = YAML().load(texts[0].decode())
    _check_states({str(k): v for k, v in doc.items()}, run)


def test_a_network_run_exports_the_same_way(tmp_path):
    """``covnet up`` (lockstep, real processes over zenoh on loopback) of a short many-target
    config: the exported truths and tracks give the network run's own OSPA / GOSPA."""
    cfg = _config(tmp_path, "multitarget", 5, allocation={"metrics": ["abs_trace"]})
    run = tmp_path / "mt-up"
    _covnet("up", str(cfg), "--out", str(run), "--no-figures")
    assert json.loads((run / "run.json").read_text())["status"] == "completed"
    doc = _export(run, tmp_path)
    _check_states(doc, run)
    assert _check_against_covnet(doc, run) == 5


def test_one_target_ospa_is_the_cut_position_error(tmp_path):
    """The paper run (one target, no OSPA of its own): Stone Soup's OSPA with one truth and
    one track is ``min(c, position error)`` per scan, covnet.core.ospa's too; GOSPA with both
    present is the error below ``c`` and ``c`` (a missed and a false target: ``(c^p/2 ·
    2)^(1/p)``) at or beyond; with ``c`` above every error the root mean square of OSPA is the
    summary's ``rmse_position``."""
    run, doc, a, summary = _run_exported(
        tmp_path, "paper", 12, allocation={"metrics": ["spectral", "svd"]}
    )
    for m in ("spectral", "svd"):
        err = np.hypot(*(a[f"x_est.{m}"] - a["truth"])[:, [0, 2]].T)
        truths, tracks = doc[m]["groundtruth_paths"], doc[m]["tracks"]
        c = float(np.median(err))  # some scans cut, some not
        assert (err >= c).any() and (err < c).any()
        o, g = _stone_soup_metrics(truths, tracks, c, 2.0)
        np.testing.assert_allclose(o, np.minimum(c, err), rtol=RTOL, atol=0)
        np.testing.assert_allclose(g, np.minimum(c, err), rtol=RTOL, atol=0)
        X, Y = a["truth"][:, None, [0, 2]], a[f"x_est.{m}"][:, None, [0, 2]]
        np.testing.assert_allclose(o, [ospa(X[k], Y[k], c) for k in range(12)], rtol=RTOL)
        big = 2.0 * float(err.max())
        o, _ = _stone_soup_metrics(truths, tracks, big, 2.0)
        rmse = summary["metrics"][m]["rmse_position"]
        assert np.sqrt(np.mean(o**2)) == pytest.approx(rmse, rel=RTOL)


def test_a_mobile_run_agrees_with_covnet_core_ospa(tmp_path):
    """A mobile run keeps no OSPA of its own: Stone Soup's on the export equals
    covnet.core.ospa's on the run's arrays (rows 0..K, at t = k T)."""
    cfg = _config(tmp_path, "mobile", 10, compare_exact=False)
    run = tmp_path / "mobile"
    _covnet("run", str(cfg), "--out", str(run), "--no-figures")
    doc = _export(run, tmp_path)
    assert list(doc) == ["lp"]
    _check_states(doc, run)
    a = load_arrays(run / "arrays.npz")
    c, p = 20.0, 2.0
    o, g = _stone_soup_metrics(doc["lp"]["groundtruth_paths"], doc["lp"]["tracks"], c, p)
    X, Y = a["truth"][:, :, [0, 2]], a["x_est"][:, :, [0, 2]]
    assert o.size == X.shape[0] == 11
    np.testing.assert_allclose(o, [ospa(X[k], Y[k], c, p) for k in range(11)], rtol=RTOL)
    np.testing.assert_allclose(g, [gospa(X[k], Y[k], c, p).distance for k in range(11)], rtol=RTOL)


def test_stone_soup_ospa_picks_its_assignment_by_distance():
    """The one known difference (module docstring), on sets closer than their errors: Stone
    Soup 1.9.1's OSPA (p = 2) is never below covnet's (the optimum of OSPA's definition) and
    sometimes above it; GOSPA is the same in both."""
    rng = np.random.default_rng(7)
    t = datetime(2000, 1, 1)
    om = OSPAMetric(c=100.0, p=2.0, measure=Euclidean())
    gm = GOSPAMetric(c=100.0, p=2.0, measure=Euclidean())
    above = 0
    for _ in range(300):
        X, Y = rng.uniform(0, 10, (3, 2)), rng.uniform(0, 10, (3, 2))
        xs = [State(x.reshape(2, 1), timestamp=t) for x in X]
        ys = [State(y.reshape(2, 1), timestamp=t) for y in Y]
        theirs = om.compute_OSPA_distance(ys, xs).value
        ours = ospa(X, Y, 100.0, 2.0)
        assert theirs >= ours * (1 - RTOL)
        above += theirs > ours * (1 + RTOL)
        g, _ = gm.compute_gospa_metric(ys, xs)
        assert g.value["distance"] == pytest.approx(gospa(X, Y, 100.0, 2.0).distance, rel=RTOL)
    assert above > 0


def test_a_surveillance_run_exports_its_confirmed_tracks_and_gives_covnets_gospa(tmp_path):
    """A surveillance run (targets that appear and leave, tracks started from detections in
    clutter): the export holds each target while it exists and each confirmed track while it is
    confirmed, with the track's own id; Stone Soup's OSPA and GOSPA on it are covnet's at every
    scan with a target or a confirmed track (Stone Soup's timestamps), and covnet's are 0 at
    the others (nothing against nothing)."""
    # its own length: targets enter until scan 60
    run, doc, a, summary = _run_exported(tmp_path, "surveillance", 100)
    c, p = summary["ospa"]["cutoff_m"], summary["ospa"]["order"]
    (m,) = (str(x) for x in a["metrics"])
    truths, tracks = doc[m]["groundtruth_paths"], doc[m]["tracks"]
    assert all(t.id.startswith("track-") for t in tracks) and len(tracks) >= 2
    assert {t.id for t in truths} <= {str(x) for x in a["truth_ids"]}
    stamps = sorted({s.timestamp for x in (*truths, *tracks) for s in x.states})
    scans = [round((s - ex.EPOCH).total_seconds() / float(a["t"][0])) for s in stamps]
    o, g = _stone_soup_metrics(truths, tracks, c, p)
    assert o.size == len(scans) >= 20
    idx = np.array(scans) - 1
    np.testing.assert_allclose(o, a[f"ospa.{m}"][idx], rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(g, a[f"gospa.{m}"][idx], rtol=RTOL, atol=1e-12)
    rest = np.setdiff1d(np.arange(100), idx)
    assert np.all(a[f"gospa.{m}"][rest] == 0.0) and np.all(a[f"ospa.{m}"][rest] == 0.0)
    # the confirmed tracks' rows, no other
    rows = a[f"track_rows.{m}"]
    assert sum(len(t.states) for t in tracks) == int((rows[:, 2] == 1).sum())
    assert sum(len(t.states) for t in truths) == int(a["exists"].sum())
