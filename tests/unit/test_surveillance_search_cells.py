"""Search cells: grid geometry, the undetected mass updates, coverage, the allocator's term."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from covnet.core.sensor_models import FieldOfView, RangeBearingModel
from covnet.core.surveillance.search_cells import (
    SearchGrid,
    after_search,
    birth_intensity_per_cell,
    cell_found,
    cell_value,
    coverage_of,
    grow,
    remove_found,
    uniform_mass,
)

GRID = SearchGrid(0.0, 200.0, -300.0, 0.0, nx=2, ny=3)  # cells 100 x 100


def test_grid_geometry() -> None:
    assert GRID.n_cells == 6 and GRID.cell_size == (100.0, 100.0) and GRID.cell_area == 1e4
    np.testing.assert_array_equal(GRID.boxes()[1], [100.0, 200.0, -300.0, -200.0])
    np.testing.assert_array_equal(GRID.boxes()[2], [0.0, 100.0, -200.0, -100.0])
    np.testing.assert_array_equal(GRID.centres()[5], [150.0, -50.0])
    pts = [[50.0, -250.0], [100.0, -250.0], [200.0, 0.0], [0.0, -300.0], [-1.0, -10.0], [10.0, 1.0]]
    np.testing.assert_array_equal(GRID.cell_of(pts), [0, 1, 5, 0, -1, -1])
    # every centre lies in its own cell
    np.testing.assert_array_equal(GRID.cell_of(GRID.centres()), np.arange(6))


def test_mass_updates() -> None:
    u = uniform_mass(GRID, 3.0)
    np.testing.assert_allclose(u, 0.5)
    u = grow(u, [0.1, 0, 0, 0, 0, 0.2])
    np.testing.assert_allclose(u, [0.6, 0.5, 0.5, 0.5, 0.5, 0.7])
    v = after_search(u, [[0.9], [], [0.5, 0.5], [1.0], [0.0], []])
    np.testing.assert_allclose(v, [0.06, 0.5, 0.125, 0.0, 0.5, 0.7])
    w = remove_found(v, [1, 1, 5, -1])
    np.testing.assert_allclose(w, [0.06, 0.0, 0.125, 0.0, 0.5, 0.0])
    with pytest.raises(ValueError, match="searched_by"):
        after_search(u, [[0.5]])
    with pytest.raises(ValueError, match="pd"):
        after_search(u, [[1.5]] * 6)
    with pytest.raises(ValueError, match="u:"):
        grow([-1.0] * 6, [0.0] * 6)


def test_search_update_is_the_expected_finds() -> None:
    """Monte Carlo: Poisson(u) targets in a cell, each found by some searcher with
    1 − Π(1 − pd): the mean undetected count after the search is u Π(1 − pd)."""
    rng = np.random.default_rng(8)
    u, pds = 2.5, [0.6, 0.3]
    n = rng.poisson(u, 200_000)
    missed = rng.binomial(n, (1 - 0.6) * (1 - 0.3))
    assert missed.mean() == pytest.approx(after_search([u], [pds])[0], rel=0.01)


def test_cell_value_is_the_spec_term_plus_a_constant() -> None:
    rng = np.random.default_rng(1)
    pds = rng.uniform(0.1, 0.95, 4).tolist()
    lam, u = 3.0, 0.7
    terms = {}
    for k in range(5):
        for S in itertools.combinations(range(4), k):
            p = [pds[j] for j in S]
            spec = -lam * u * (1.0 - math.prod(1.0 - q for q in p))
            assert cell_value(u, lam, p) == pytest.approx(spec + lam * u, abs=1e-14)
            assert cell_found(u, lam, p) == pytest.approx(-spec, abs=1e-14)
            assert cell_value(u, lam, p) >= 0.0
            terms[S] = cell_value(u, lam, p)
    # Loewner-like monotonicity: one more searcher never raises the term
    for S, v in terms.items():
        for j in set(range(4)) - set(S):
            assert terms[tuple(sorted((*S, j)))] <= v
    assert cell_value(u, 0.0, pds) == 0.0  # λ = 0: searching is worth nothing


def test_coverage_by_the_cell_centre() -> None:
    grid = SearchGrid(-1000.0, 1000.0, -1000.0, 1000.0, nx=4, ny=4)
    m = RangeBearingModel(sensor_xy=(0.0, 0.0), sigma_r=1.0, sigma_bearing=1e-3, max_range_m=400.0)
    cov = coverage_of(grid, m)
    d = np.hypot(*grid.centres().T)
    np.testing.assert_array_equal(cov, d <= 400.0)
    assert cov.sum() == 4  # the four centres at (±250, ±250)
    east = RangeBearingModel(
        sensor_xy=(0.0, 0.0), sigma_r=1.0, sigma_bearing=1e-3, fov=FieldOfView(0.0, 60.0)
    )
    c = grid.centres()
    np.testing.assert_array_equal(
        coverage_of(grid, east), np.abs(np.degrees(np.arctan2(c[:, 1], c[:, 0]))) <= 60.0
    )


def test_birth_intensity_splits_by_area() -> None:
    b = birth_intensity_per_cell(GRID, [(50.0, 150.0, -300.0, -250.0)], 2.0)
    np.testing.assert_allclose(b, [1.0, 1.0, 0, 0, 0, 0])
    b = birth_intensity_per_cell(
        GRID, [(0.0, 100.0, -300.0, -200.0), (0.0, 200.0, -100.0, 0.0)], 3.0
    )
    np.testing.assert_allclose(b, [1.0, 0, 0, 0, 1.0, 1.0])
    assert birth_intensity_per_cell(GRID, [], 1.0).sum() == 0.0


def test_grid_checks_name_the_field() -> None:
    with pytest.raises(ValueError, match="xmin < xmax"):
        SearchGrid(1.0, 0.0, 0.0, 1.0, 1, 1)
    with pytest.raises(ValueError, match="nx"):
        SearchGrid(0.0, 1.0, 0.0, 1.0, 0, 1)
