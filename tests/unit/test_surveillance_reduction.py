"""Spec surveillance.md §6: with P_D = 1, no clutter and well-separated targets, initiation +
JPDA + M-of-N confirms every target within n dwells of its first detection and starts no
false track."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.kalman import predict
from covnet.core.manoeuvre import manoeuvring_trajectory
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.core.sensor_models import PositionModel, RangeBearingModel, SensorModel
from covnet.core.surveillance.births import ScheduledTarget, simulate_truth
from covnet.core.surveillance.continuity import ContinuityFrame, evaluate_continuity
from covnet.core.surveillance.jpda import jpda_update
from covnet.core.surveillance.tracks import TrackManager, TrackRules, is_hit

T, SIGMA_A, K = 1.0, 0.5, 12
PG = 1.0 - 1e-9  # a correct return essentially never falls outside its gate


def _run(model: SensorModel, m: int, n: int, seed: int):
    rng = np.random.default_rng(seed)
    starts = [  # 3 km apart, up to 25 m/s
        ([2000.0, 20.0, 2000.0, 0.0], 1),
        ([5000.0, -15.0, 2500.0, 10.0], 3),
        ([3500.0, 0.0, 5500.0, -25.0], 6),
    ]
    sched = [
        ScheduledTarget(manoeuvring_trajectory(x0, T, SIGMA_A, K, rng), appears_at_scan=a)
        for x0, a in starts
    ]
    truth = simulate_truth(sched, K, rng)
    F, Q = cv_transition(T), dwna_process_noise(T, SIGMA_A)
    rules = TrackRules(confirm_m=m, confirm_n=n, velocity_std=30.0, delete_after_misses=2)
    mgr = TrackManager(rules)
    frames = []
    for k in range(1, K + 1):
        _, X = truth.at_scan(k)
        Z = model.h(X) + rng.standard_normal((X.shape[0], model.dim_z)) @ model.L.T
        for t in mgr.live():
            mgr.set_estimate(t.id, predict(t.estimate, F, Q))
        live = mgr.live()
        res = jpda_update([t.estimate for t in live], Z, model, 0.0, pd=1.0, gate_probability=PG)
        assert res.exact
        for t, u in zip(live, res.updates, strict=True):
            mgr.record_dwell(t.id, u.posterior, is_hit(u.beta0, u.gated.size), k)
        mgr.initiate(Z, res.ungated_rows(Z.shape[0]), model, k)
        mgr.check_covariance(k)
        ids, X = truth.at_scan(k)
        conf = mgr.confirmed()
        frames.append(
            ContinuityFrame(
                k,
                ids,
                X[:, [0, 2]],
                np.array([t.id for t in conf], dtype=np.intp),
                np.array([t.estimate.x[[0, 2]] for t in conf]).reshape(-1, 2),
            )
        )
    return mgr, evaluate_continuity(frames, c=200.0)


MODELS = {
    "position": PositionModel(sigma_x=10.0, sigma_y=15.0, rho=0.2, pd=1.0),
    "range_bearing": RangeBearingModel(
        sensor_xy=(0.0, 0.0), sigma_r=20.0, sigma_bearing=2e-3, pd=1.0
    ),
}


@pytest.mark.parametrize("kind", sorted(MODELS))
@pytest.mark.parametrize(("m", "n"), [(2, 3), (3, 3), (3, 5)])
@pytest.mark.parametrize("seed", range(4))
def test_every_target_confirmed_within_n_dwells_and_no_false_track(
    kind: str, m: int, n: int, seed: int
) -> None:
    mgr, rep = _run(MODELS[kind], m, n, seed)
    # one track per target, never deleted, every one confirmed m − 1 dwells after its birth
    assert mgr.next_id == 3 and mgr.deleted == []
    assert rep.time_to_confirm == {0: m - 1, 1: m - 1, 2: m - 1}
    assert max(rep.time_to_confirm.values()) <= n - 1
    assert all(s.n_false == 0 for s in rep.scans)
    assert rep.n_breaks == 0 and rep.n_switches == 0
    for t in mgr.confirmed():
        assert t.confirmed_scan == t.born_scan + m - 1
