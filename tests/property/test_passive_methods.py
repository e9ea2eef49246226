"""Generic checks of every registered association method (``sorted(METHODS)``): a new entry in
the registry gets them without new test code."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.core.passive import METHODS, Association, PassiveScan
from covnet.passive.scene import PAPER_SENSORS, SceneModel, draw, formation

NAMES = sorted(METHODS)


def _scene(form: str, d: float, sigma: float, clutter: bool, trial: int):
    model = SceneModel(
        PAPER_SENSORS,
        formation(form, d),
        np.full(3, sigma),
        np.full(3, sigma),
        0.95 if clutter else 1.0,
        0.25 if clutter else 0.0,
    )
    return draw(model, 21, trial), model.params()


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=15)
@given(
    st.sampled_from(["horizontal", "cross"]),
    st.sampled_from([0.5, 1.0, 2.0]),
    st.sampled_from([1e-3, 3e-3]),
    st.booleans(),
    st.integers(0, 1000),
    st.integers(0, 2**31 - 1),
)
def test_method_contract(name, form, d, sigma, clutter, trial, perm_seed):
    scene, params = _scene(form, d, sigma, clutter, trial)
    a = METHODS[name](scene.scan, params)
    assert isinstance(a, Association)
    assert a.status == 0, a.message
    n = scene.scan.counts
    for Z in (a.triples, a.tuples):
        assert Z.ndim == 2 and Z.shape[1] == 3
        for s in range(3):
            real = Z[:, s][Z[:, s] >= 0]
            assert len(set(real.tolist())) == len(real)  # each measurement at most once
            assert np.all(real < n[s])
    assert np.all(a.triples >= 0)
    full = {tuple(t) for t in a.tuples.tolist() if min(t) >= 0}
    assert full == {tuple(t) for t in a.triples.tolist()}
    # the order of the lists carries no information
    rng = np.random.default_rng(perm_seed)
    perms = [rng.permutation(k) for k in n]
    scan2 = PassiveScan(
        scene.scan.sensors, tuple(z[p] for z, p in zip(scene.scan.z, perms, strict=True))
    )
    b = METHODS[name](scan2, params)
    back = {tuple(int(perms[s][t[s]]) for s in range(3)) for t in b.triples}
    if name in ("cot", "milp"):
        assert back == {tuple(t) for t in a.triples.tolist()}
    assert b.cost == pytest.approx(a.cost, rel=1e-6, abs=1e-6) or name == "lr"


@pytest.mark.parametrize("name", NAMES)
def test_noise_free_horizontal_scan_is_solved_exactly(name):
    scene, params = _scene("horizontal", 1.0, 1e-3, False, 0)
    model = SceneModel(
        PAPER_SENSORS, formation("horizontal", 1.0), np.full(3, 1e-9), np.full(3, 1e-9)
    )
    clean = draw(model, 21, 0)
    a = METHODS[name](clean.scan, params)
    assert {tuple(t) for t in a.triples.tolist()} == {tuple(t) for t in clean.truth.tolist()}
