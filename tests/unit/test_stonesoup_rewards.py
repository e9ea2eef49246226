"""covnet's ``uncertainty_reward`` and ``expected_kl`` give Stone Soup's own reward values
(``stonesoup.sensormanager.reward.UncertaintyRewardFunction`` and ``ExpectedKLDivergence``) on the
same predicted and updated Gaussian states: Stone Soup's predictor, updater, linear-Gaussian
measurement models and sensors, its reward functions called as its sensor managers call them
(a configuration of sensors and their actions, the tracks, the time).

Stone Soup's ``ExpectedKLDivergence`` with several separate sensors adds the KL of each
sequential update in the iteration order of a ``set`` of sensor copies, which changes from call
to call; covnet's ``expected_kl`` is the order-free KL of the joint update, Stone Soup's value for
one sensor or for the subset as one stacked sensor.  Both are checked here, and the sequential
sums against :func:`covnet.core.allocation.policies.expected_kl_sequential`."""

from __future__ import annotations

import datetime
import itertools

import numpy as np
import pytest

pytest.importorskip("stonesoup")

from stonesoup.base import Property  # noqa: E402
from stonesoup.models.measurement.linear import LinearGaussian  # noqa: E402
from stonesoup.models.transition.linear import (  # noqa: E402
    CombinedLinearGaussianTransitionModel,
    ConstantVelocity,
)
from stonesoup.predictor.kalman import KalmanPredictor  # noqa: E402
from stonesoup.sensor.sensor import SimpleSensor  # noqa: E402
from stonesoup.sensormanager.reward import (  # noqa: E402
    ExpectedKLDivergence,
    UncertaintyRewardFunction,
)
from stonesoup.types.state import GaussianState  # noqa: E402
from stonesoup.types.track import Track  # noqa: E402
from stonesoup.updater.kalman import ExtendedKalmanUpdater  # noqa: E402

from covnet.core.allocation.constraints import Constraints  # noqa: E402
from covnet.core.allocation.policies import (  # noqa: E402
    expected_kl,
    expected_kl_sequential,
    uncertainty_reward,
)
from covnet.core.allocation.policies_many import OFF, total_reward  # noqa: E402
from covnet.core.allocation.policy_registry import POLICIES  # noqa: E402

T0 = datetime.datetime(2025, 1, 1)
DT = datetime.timedelta(seconds=1)
RTOL = 1e-9


class LinearSensor(SimpleSensor):
    """The minimal Stone Soup sensor: a linear-Gaussian model, every target detectable (or
    only those of one ``target`` label, for the many-target case), no clutter, no actions."""

    model: LinearGaussian = Property(doc="measurement model")
    target: int = Property(default=None, doc="detects only tracks with this metadata label")

    @property
    def measurement_model(self):
        return self.model

    def is_detectable(self, state, measurement_model=None):
        return self.target is None or state.metadata.get("target") == self.target

    def is_clutter_detectable(self, state):
        return True


def _correlated(sx, sy, rho):
    return np.array([[sx * sx, rho * sx * sy], [rho * sx * sy, sy * sy]])


#: mappings over [x, vx, y, vy] and noise covariances: position sensors like the paper's, an
#: x-only, a velocity and a y-only one
SPECS = [
    ((0, 2), _correlated(21.1, 8.2, 0.82)),
    ((0, 2), _correlated(8.22, 20.3, 0.78)),
    ((0,), np.array([[30.0**2]])),
    ((1, 3), _correlated(2.0, 3.0, -0.3)),
    ((2,), np.array([[15.0**2]])),
]


def _models():
    return [LinearGaussian(4, mapping, R) for mapping, R in SPECS]


def _gains(models):
    out = []
    for m in models:
        H = m.matrix()
        out.append(H.T @ np.linalg.inv(m.covar()) @ H)
    return np.array(out)


def _setup(seed=0, target=None):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(4, 4))
    P0 = A @ A.T * 50.0 + np.diag([400.0, 20.0, 400.0, 20.0])
    x0 = rng.normal(size=(4, 1)) * 100.0
    meta = None if target is None else {"target": target}
    track = Track([GaussianState(x0, P0, timestamp=T0)], init_metadata=meta)
    predictor = KalmanPredictor(
        CombinedLinearGaussianTransitionModel([ConstantVelocity(0.25), ConstantVelocity(0.25)])
    )
    P_pred = predictor.predict(track[-1], timestamp=T0 + DT).covar
    return track, predictor, np.asarray(P_pred, dtype=np.float64)


def _stonesoup_rewards(sensors, tracks, predictor):
    updater = ExtendedKalmanUpdater(measurement_model=None)
    config = {s: [] for s in sensors}
    ur = UncertaintyRewardFunction(predictor, updater)(config, tracks, T0 + DT)
    kl = ExpectedKLDivergence(predictor, updater)(config, tracks, T0 + DT)
    return float(ur), float(kl)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_one_sensor_both_rewards_equal_stonesoups(seed):
    track, predictor, P_pred = _setup(seed)
    models = _models()
    G = _gains(models)
    for j, m in enumerate(models):
        ur, kl = _stonesoup_rewards([LinearSensor(model=m)], {track}, predictor)
        assert uncertainty_reward(P_pred, G, [j]) == pytest.approx(ur, rel=RTOL)
        assert expected_kl(P_pred, G, [j]) == pytest.approx(kl, rel=RTOL)


@pytest.mark.parametrize("seed", [0, 1])
def test_several_sensors_uncertainty_equals_stonesoups_in_any_order(seed):
    """Stone Soup adds ``‖P_prev‖_F − ‖P_new‖_F`` per sequential update: a telescoping sum,
    covnet's ``‖P⁻‖_F − ‖P(D)‖_F`` whatever order its set of sensors is iterated in."""
    track, predictor, P_pred = _setup(seed)
    models = _models()
    G = _gains(models)
    for k in (2, 3, 5):
        for D in itertools.combinations(range(len(models)), k):
            for _ in range(3):  # Stone Soup's order changes from call to call
                sensors = [LinearSensor(model=models[j]) for j in D]
                ur, _ = _stonesoup_rewards(sensors, {track}, predictor)
                assert uncertainty_reward(P_pred, G, D) == pytest.approx(ur, rel=RTOL)


@pytest.mark.parametrize("seed", [0, 1])
def test_expected_kl_is_stonesoups_for_the_subset_as_one_stacked_sensor(seed):
    track, predictor, P_pred = _setup(seed)
    G = _gains(_models())
    for k in (2, 3, 5):
        for D in itertools.combinations(range(len(SPECS)), k):
            mapping = tuple(i for j in D for i in SPECS[j][0])
            R = np.zeros((len(mapping), len(mapping)))
            at = 0
            for j in D:
                m = len(SPECS[j][0])
                R[at : at + m, at : at + m] = SPECS[j][1]
                at += m
            stacked = LinearSensor(model=LinearGaussian(4, mapping, R))
            ur, kl = _stonesoup_rewards([stacked], {track}, predictor)
            assert expected_kl(P_pred, G, D) == pytest.approx(kl, rel=RTOL)
            assert uncertainty_reward(P_pred, G, D) == pytest.approx(ur, rel=RTOL)


def test_stonesoups_kl_of_separate_sensors_is_a_sequential_sum_in_its_set_order():
    """With separate sensors Stone Soup's value is ``expected_kl_sequential`` for one of the
    orders of the subset (its set's iteration order), not a function of the subset alone."""
    track, predictor, P_pred = _setup(3)
    models = _models()
    G = _gains(models)
    D = (0, 1, 3)
    by_order = {o: expected_kl_sequential(P_pred, G, o) for o in itertools.permutations(D)}
    for _ in range(30):
        _, kl = _stonesoup_rewards([LinearSensor(model=models[j]) for j in D], {track}, predictor)
        match = [o for o, v in by_order.items() if v == pytest.approx(kl, rel=RTOL)]
        assert match, (kl, by_order)
    assert len(set(round(v, 9) for v in by_order.values())) > 1  # the order does matter
    # covnet's reward is the joint update's, order-free
    assert expected_kl(P_pred, G, D) == pytest.approx(expected_kl(P_pred, G, D[::-1]), rel=1e-14)


def test_the_brute_force_picks_the_subset_with_stonesoups_best_reward():
    track, predictor, P_pred = _setup(4)
    models = _models()
    G = _gains(models)
    for K in (1, 2, 3):
        subsets = [
            D for k in range(1, K + 1) for D in itertools.combinations(range(len(models)), k)
        ]
        values = {
            D: _stonesoup_rewards([LinearSensor(model=models[j]) for j in D], {track}, predictor)[0]
            for D in subsets
        }
        best = max(subsets, key=lambda D: values[D])
        d = POLICIES["uncertainty_reward"].decide(P_pred, G, Constraints(), budget=K)
        assert d.subset == best and len(best) == K
        assert d.score == pytest.approx(values[best], rel=RTOL)


def test_many_targets_the_sum_over_tracks_is_stonesoups():
    """Two tracks; each sensor detects only the track it dwells on (the assignment): Stone
    Soup's rewards over both tracks equal covnet's per-target sums (``total_reward``)."""
    tracks, P_list = [], []
    for t in range(2):
        track, predictor, P = _setup(10 + t, target=t)
        tracks.append(track)
        P_list.append(P)
    P_pred = np.array(P_list)
    models = _models()
    G = _gains(models)
    J = np.stack([G, G], axis=1)
    for a in [(0, 1, OFF, OFF, OFF), (0, OFF, 1, OFF, OFF), (1, 0, OFF, 0, OFF)]:
        sensors = [LinearSensor(model=models[j], target=t) for j, t in enumerate(a) if t != OFF]
        ur, kl = _stonesoup_rewards(sensors, set(tracks), predictor)
        assert total_reward("uncertainty_reward", P_pred, J, a) == pytest.approx(ur, rel=RTOL)
        if all(list(a).count(t) <= 1 for t in range(2)):  # one update per track: no order
            assert total_reward("expected_kl", P_pred, J, a) == pytest.approx(kl, rel=RTOL)
