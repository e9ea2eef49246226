"""The duplicate rule of the surveillance centre: of two live tracks on one target (inside the
χ² gate of their summed position covariance) a tentative one is deleted before a confirmed one,
then the less certain one, then the younger.  It deleted the less certain one alone: a fresh
tentative track from one return of a fine sensor replaced the target's confirmed track (a track
break and a new id for nothing, found on a ``pd: 1`` scenario)."""

from __future__ import annotations

import numpy as np
import pytest
from test_surveillance_run import base

from covnet.core.gaussian import Gaussian
from covnet.core.surveillance.tracks import Track, TrackState
from covnet.covariance_control import surveillance
from covnet.covariance_control.config import from_dict
from covnet.covariance_control.surveillance_centre import SurveillanceCentre

AT = np.array([10_000.0, 0.0, 10_000.0, 0.0])  # inside the area of base()


def _track(tid: int, state: TrackState, pos_var: float, dx: float = 0.0) -> Track:
    x = AT + np.array([dx, 0.0, 0.0, 0.0])
    P = np.diag([pos_var, 100.0, pos_var, 100.0])
    confirmed = 1 if state is TrackState.CONFIRMED else None
    return Track(tid, state, Gaussian(x, P), (True,), 1, 0, 1, confirmed)


def _survivors(*tracks: Track) -> list[int]:
    centre = SurveillanceCentre(surveillance.build(from_dict(base(scans=4))))
    for t in tracks:
        centre.manager._store(t)
    centre._too_wide(3)
    assert all(t.deleted_reason == "duplicate" for t in centre.manager.deleted)
    return [t.id for t in centre.manager.live()]


@pytest.mark.parametrize(
    "a,b,kept",
    [
        # the older confirmed track stays although the young tentative one is more certain
        ((TrackState.CONFIRMED, 400.0), (TrackState.TENTATIVE, 50.0), 1),
        ((TrackState.TENTATIVE, 50.0), (TrackState.CONFIRMED, 400.0), 2),
        # the same state: the more certain one, whichever is older
        ((TrackState.CONFIRMED, 400.0), (TrackState.CONFIRMED, 50.0), 2),
        ((TrackState.TENTATIVE, 50.0), (TrackState.TENTATIVE, 400.0), 1),
        # a tie: the older
        ((TrackState.CONFIRMED, 100.0), (TrackState.CONFIRMED, 100.0), 1),
    ],
)
def test_which_duplicate_stays(a, b, kept):
    assert _survivors(_track(1, *a), _track(2, *b, dx=5.0)) == [kept]


def test_tracks_apart_are_no_duplicates():
    far = _track(2, TrackState.TENTATIVE, 50.0, dx=2_000.0)
    assert _survivors(_track(1, TrackState.CONFIRMED, 400.0), far) == [1, 2]
