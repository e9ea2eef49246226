"""Scenes (spec §2, §3): geometry, determinism, common random numbers, truth, clutter."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.passive.model import angles, bearing_to_azimuth, wrap
from covnet.passive.scene import PAPER_SENSORS, SceneModel, draw, formation, score


def test_formations_follow_the_paper_numbering():
    h = formation("horizontal", 0.5)
    np.testing.assert_allclose(h[:, :2], [[5, 5], [5.5, 5], [4.5, 5], [6, 5], [4, 5]])
    c = formation("cross", 2.0)
    np.testing.assert_allclose(c[:, :2], [[5, 5], [7, 5], [3, 5], [5, 7], [5, 3]])
    assert np.all(c[:, 2] == 1.0)
    with pytest.raises(ValueError, match="unknown formation"):
        formation("diagonal", 1.0)


def test_angle_conventions():
    s = np.zeros((1, 3))
    a = angles(s, np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 1.0]]))
    assert a[0, 0, 0] == pytest.approx(np.pi / 2) and a[0, 0, 1] == 0.0
    assert a[1, 0, 0] == pytest.approx(np.pi) and a[1, 0, 1] == pytest.approx(np.pi / 4)
    assert wrap(np.array([-np.pi]))[0] == pytest.approx(np.pi)
    beta = np.array([0.0, 0.3])  # compass bearing: cot α = tan β
    np.testing.assert_allclose(1 / np.tan(bearing_to_azimuth(beta[1:])), np.tan(beta[1:]))
    assert bearing_to_azimuth(beta[:1])[0] == pytest.approx(np.pi / 2)


def _model(sigma=1e-3, d=1.0, form="cross", pd=1.0, rate=0.0):
    return SceneModel(
        PAPER_SENSORS, formation(form, d), np.full(3, sigma), np.full(3, sigma), pd, rate
    )


def test_draw_is_deterministic_and_truth_is_consistent():
    m = _model(pd=0.9, rate=1.5)
    a, b = draw(m, 3, 7), draw(m, 3, 7)
    for s in range(3):
        np.testing.assert_array_equal(a.scan.z[s], b.scan.z[s])
        np.testing.assert_array_equal(a.labels[s], b.labels[s])
    assert not np.array_equal(draw(m, 3, 8).scan.z[0], a.scan.z[0])
    for t, tgt in zip(a.truth, a.truth_targets, strict=True):
        for s in range(3):
            assert a.labels[s][t[s]] == tgt
    seen_by_all = set.intersection(*(set(lab[lab >= 0].tolist()) for lab in a.labels))
    assert set(a.truth_targets.tolist()) == seen_by_all


def test_common_random_numbers_across_sigma_and_spacing():
    """The normalised noise of every target measurement is the same in every cell."""
    for trial in range(5):
        ref = None
        for sigma, d, form in ((1e-3, 0.5, "cross"), (5e-3, 2.0, "horizontal")):
            m = _model(sigma=sigma, d=d, form=form)
            sc = draw(m, 1, trial)
            noise = []
            for s in range(3):
                true = angles(PAPER_SENSORS[s : s + 1], m.targets[sc.labels[s]])[:, 0]
                noise.append((wrap(sc.scan.z[s] - true)) / sigma)
            noise = np.concatenate(noise)
            if ref is None:
                ref = noise
            np.testing.assert_allclose(noise, ref, atol=1e-9)


def test_clean_scene_has_five_targets_everywhere():
    sc = draw(_model(), 1, 0)
    assert sc.scan.counts == (5, 5, 5)
    assert sc.truth.shape == (5, 3)
    assert score(sc.truth, sc.truth) == (5, 5, 5, True)


def test_clutter_rate_and_window():
    m = _model(pd=0.95, rate=2.0)
    centre = angles(PAPER_SENSORS, m.targets.mean(axis=0))
    counts = []
    for trial in range(400):
        sc = draw(m, 2, trial)
        for s in range(3):
            c = sc.scan.z[s][sc.labels[s] < 0]
            counts.append(len(c))
            assert np.all(np.abs(wrap(c[:, 0] - centre[s, 0])) <= 0.05 + 1e-12)
            assert np.all(np.abs(c[:, 1] - centre[s, 1]) <= 0.05 + 1e-12)
    assert np.mean(counts) == pytest.approx(2.0, abs=0.15)
    assert m.clutter_density == pytest.approx(200.0)


def test_score_counts():
    G = np.array([[0, 1, 2], [1, 0, 0]])
    Z = np.array([[0, 1, 2], [2, 2, 1]])
    assert score(G, Z) == (1, 2, 2, False)
    assert score(np.zeros((0, 3)), np.zeros((0, 3))) == (0, 0, 0, True)
