"""Hypothesis checks of the cot method (spec §11 items 1 and 4): the noise-free identities on
random layouts (sensor altitudes may differ), and the indicator analysis' independence of the
order of the measurement lists and of the candidate rows."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.core.passive.cotangent import (
    associate_cot,
    azimuth_statistic,
    height_statistic,
    indicator_analysis,
)
from covnet.core.passive.model import PassiveScan, angles
from covnet.passive.scene import PAPER_SENSORS, SceneModel, draw, formation

coord = st.floats(-20.0, 20.0, allow_nan=False, allow_infinity=False)
alt = st.floats(-0.5, 0.5, allow_nan=False, allow_infinity=False)


@st.composite
def layouts(draw_):
    sensors = np.array([[draw_(coord), draw_(coord), draw_(alt)] for _ in range(3)])
    target = np.array([draw_(coord), draw_(coord), draw_(st.floats(1.0, 5.0))])
    return sensors, target


def _well_posed(sensors: np.ndarray, target: np.ndarray) -> bool:
    d = target[:2] - sensors[:, :2]
    r = np.hypot(d[:, 0], d[:, 1])
    if r.min() < 1.0:
        return False
    az = np.arctan2(d[:, 1], d[:, 0])
    if np.abs(np.sin(az)).min() < 0.05:  # a LOS (nearly) along x: k = cot α huge
        return False
    # both height pairs need non-parallel projected LOS
    return abs(np.sin(az[2] - az[0])) > 0.05 and abs(np.sin(az[2] - az[1])) > 0.05


@given(layouts(), st.sampled_from(["cot", "sine"]))
def test_noise_free_identities_on_random_layouts(layout, form):
    sensors, target = layout
    assume(_well_posed(sensors, target))
    ang = angles(sensors, target)  # (3, 2)
    sig = np.array([1e-3, 2e-3, 3e-3])
    F, sF = azimuth_statistic(sensors, *ang[:, 0], sig, form=form)
    assert abs(F) < 1e-9 * sF
    e, se, ok = height_statistic(sensors, ang[None, :, 0], ang[None, :, 1], sig, sig[::-1])
    assert ok.all()
    assert np.all(np.abs(e) < 1e-9 * se)


def _relabel(triples: np.ndarray, perms: list[np.ndarray]) -> set[tuple[int, ...]]:
    """Map triples of permuted lists back to the original measurement indices."""
    return {tuple(int(perms[s][t[s]]) for s in range(3)) for t in triples}


@given(
    st.integers(0, 10_000),
    st.sampled_from(["horizontal", "cross"]),
    st.sampled_from([0.5, 1.0]),
    st.sampled_from([3e-3, 5e-3]),
    st.integers(0, 2**31 - 1),
)
def test_cot_does_not_depend_on_the_order_of_the_lists(trial, form, d, sigma, perm_seed):
    model = SceneModel(
        PAPER_SENSORS, formation(form, d), np.full(3, sigma), np.full(3, sigma), 0.95, 1.0
    )
    scene = draw(model, 11, trial)
    params = model.params()
    base = associate_cot(scene.scan, params)
    rng = np.random.default_rng(perm_seed)
    perms = [rng.permutation(z.shape[0]) for z in scene.scan.z]
    scan2 = PassiveScan(
        scene.scan.sensors, tuple(z[p] for z, p in zip(scene.scan.z, perms, strict=True))
    )
    other = associate_cot(scan2, params)
    assert _relabel(other.triples, perms) == {tuple(t) for t in base.triples.tolist()}
    assert other.info == base.info
    Z = base.triples
    for s in range(3):
        assert len(set(Z[:, s].tolist())) == len(Z)


@given(
    arrays(np.int64, st.tuples(st.integers(1, 25), st.just(3)), elements=st.integers(0, 4)),
    st.integers(0, 2**31 - 1),
)
def test_indicator_analysis_row_order_and_disjointness(P, seed):
    rng = np.random.default_rng(seed)
    psi = rng.permutation(P.shape[0]).astype(float) + rng.random(P.shape[0])  # no exact ties
    rows = indicator_analysis(P, psi)
    Z = P[rows]
    for s in range(3):
        assert len(set(Z[:, s].tolist())) == len(Z)  # pairwise disjoint
    # maximal: every other row shares a measurement with an accepted one
    for r in range(P.shape[0]):
        assert r in set(rows.tolist()) or np.any(P[r] == Z)
    perm = rng.permutation(P.shape[0])
    rows2 = indicator_analysis(P[perm], psi[perm])
    assert sorted(perm[rows2].tolist()) == sorted(rows.tolist())
