"""Continuity metrics on hand-built scenarios whose answers are known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covnet.core.ospa import gospa, ospa
from covnet.core.surveillance.continuity import ContinuityFrame, evaluate_continuity

C = 100.0


def F(scan, truths, tracks):
    """truths / tracks: {id: (x, y)}."""
    return ContinuityFrame(
        scan,
        np.array(list(truths), dtype=np.intp),
        np.array(list(truths.values()), dtype=float).reshape(-1, 2),
        np.array(list(tracks), dtype=np.intp),
        np.array(list(tracks.values()), dtype=float).reshape(-1, 2),
    )


def test_time_to_confirm_and_cardinality() -> None:
    frames = [
        F(1, {0: (0, 0)}, {}),
        F(2, {0: (10, 0)}, {}),
        F(3, {0: (20, 0), 1: (5000, 0)}, {4: (22, 0)}),
        F(4, {0: (30, 0), 1: (5010, 0)}, {4: (31, 0), 5: (9000, 0)}),  # 5 is a false track
        F(5, {0: (40, 0), 1: (5020, 0)}, {4: (41, 0), 5: (9000, 0), 6: (5021, 0)}),
    ]
    rep = evaluate_continuity(frames, C)
    assert rep.first_scan == {0: 1, 1: 3}
    assert rep.time_to_confirm == {0: 2, 1: 2}
    assert rep.mean_time_to_confirm == 2.0 and rep.n_never_confirmed == 0
    assert [(s.n_true, s.n_confirmed) for s in rep.scans] == [
        (1, 0),
        (1, 0),
        (2, 1),
        (2, 2),
        (2, 3),
    ]
    assert [s.n_missed for s in rep.scans] == [1, 1, 1, 1, 0]
    assert [s.n_false for s in rep.scans] == [0, 0, 0, 1, 1]
    assert rep.scans[4].held == ((0, 4), (1, 6))
    assert rep.n_breaks == rep.n_switches == 0
    # GOSPA / OSPA per scan are those of covnet.core.ospa
    for f, s in zip(frames, rep.scans, strict=True):
        g = gospa(f.truth_xy, f.track_xy, C)
        assert s.gospa == g.distance and s.localisation == g.localisation
        assert s.ospa == ospa(f.truth_xy, f.track_xy, C)
    assert rep.scans[2].localisation == pytest.approx(4.0)  # (22 − 20)²


def test_break_then_new_track_is_not_a_switch() -> None:
    frames = [
        F(1, {0: (0, 0)}, {7: (1, 0)}),
        F(2, {0: (10, 0)}, {7: (11, 0)}),
        F(3, {0: (20, 0)}, {}),  # track 7 deleted while target 0 exists: a break
        F(4, {0: (30, 0)}, {9: (30, 1)}),
        F(5, {0: (40, 0)}, {9: (40, 1)}),
    ]
    rep = evaluate_continuity(frames, C)
    assert [s.breaks for s in rep.scans] == [(), (), (0,), (), ()]
    assert rep.n_breaks == 1 and rep.n_switches == 0
    assert rep.time_to_confirm == {0: 0}


def test_swap_of_labels_is_two_switches() -> None:
    frames = [
        F(1, {0: (0, 0), 1: (0, 50)}, {3: (0, 1), 4: (0, 49)}),
        F(2, {0: (10, 20), 1: (10, 30)}, {3: (10, 21), 4: (10, 29)}),
        F(3, {0: (20, 50), 1: (20, 0)}, {3: (20, 1), 4: (20, 49)}),  # labels crossed over
    ]
    rep = evaluate_continuity(frames, C)
    assert rep.scans[2].switches == ((0, 3, 4), (1, 4, 3))
    assert rep.n_switches == 2 and rep.n_breaks == 0


def test_gap_is_not_a_switch_and_leaving_is_not_a_break() -> None:
    frames = [
        F(1, {0: (0, 0)}, {7: (1, 0)}),
        F(2, {0: (10, 0)}, {7: (500, 0)}),  # too far: missed, track 7 still alive
        F(3, {0: (20, 0)}, {7: (21, 0)}),
        F(4, {}, {}),  # the target left and its track was deleted: no break
        F(5, {2: (0, 0)}, {}),
    ]
    rep = evaluate_continuity(frames, C)
    assert rep.n_switches == 0 and rep.n_breaks == 0
    assert rep.time_to_confirm == {0: 0, 2: None}
    assert rep.n_never_confirmed == 1 and rep.mean_time_to_confirm == 0.0
    assert rep.scans[3].gospa == 0.0


def test_empty_and_checks() -> None:
    rep = evaluate_continuity([], C)
    assert rep.scans == () and math.isnan(rep.mean_time_to_confirm)
    with pytest.raises(ValueError, match="increasing"):
        evaluate_continuity([F(2, {}, {}), F(2, {}, {})], C)
    with pytest.raises(ValueError, match="distinct"):
        ContinuityFrame(1, np.array([1, 1]), np.zeros((2, 2)), np.zeros(0), np.zeros((0, 2)))
    with pytest.raises(ValueError, match="track_xy"):
        ContinuityFrame(1, np.zeros(0), np.zeros((0, 2)), np.array([1]), np.zeros((2, 2)))
