"""covnet's covariance-control objective inside a Stone Soup pipeline (issue 27, Stone Soup
interop): :class:`covnet.interop.stonesoup.CovarianceControlReward` as the reward function of
Stone Soup's ``BruteForceSensorManager`` over Stone Soup's rotating radars (their actions: dwell
centres), Kalman predictor and extended Kalman updater.

- the script of the README's "Using covnet's objective in Stone Soup" paragraph: the manager's
  choice at every step is the configuration of largest reward, checked against an oracle that
  scores every configuration, and the tracks' covariances after the real updates are the ones
  the reward predicted;
- the reward's value is ``−Σ w f(P_upd[I, I], P_d)`` computed by hand with numpy (linear-Gaussian
  sensors, so ``P_upd`` has a closed form), to ``rtol 1e-9``;
- with ``P_d`` a configuration's own updated covariance that configuration scores the maximum,
  0, for every covnet metric (all have ``f(A, A) = 0``).
"""

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
from stonesoup.sensor.radar.radar import RadarRotatingBearingRange  # noqa: E402
from stonesoup.sensor.sensor import SimpleSensor  # noqa: E402
from stonesoup.sensormanager import BruteForceSensorManager  # noqa: E402
from stonesoup.types.angle import Angle  # noqa: E402
from stonesoup.types.array import StateVector  # noqa: E402
from stonesoup.types.detection import TrueDetection  # noqa: E402
from stonesoup.types.groundtruth import GroundTruthPath, GroundTruthState  # noqa: E402
from stonesoup.types.hypothesis import SingleHypothesis  # noqa: E402
from stonesoup.types.state import GaussianState  # noqa: E402
from stonesoup.types.track import Track  # noqa: E402
from stonesoup.updater.kalman import ExtendedKalmanUpdater  # noqa: E402

from covnet.core.metrics import METRICS  # noqa: E402
from covnet.interop.stonesoup import CovarianceControlReward  # noqa: E402

T0 = datetime.datetime(2025, 1, 1)
DT = datetime.timedelta(seconds=1)
POS = (0, 2)  # the positions of the state [x, vx, y, vy]


def _transition():
    return CombinedLinearGaussianTransitionModel([ConstantVelocity(0.5), ConstantVelocity(0.5)])


def _radar(x, y):
    """Stone Soup's rotating bearing-range radar: 60° field of view, dwell centres every 60°,
    20 rpm (120° in a 1 s step): 5 dwell actions per step."""
    radar = RadarRotatingBearingRange(
        position_mapping=POS,
        noise_covar=np.diag([np.radians(1.0) ** 2, 5.0**2]),
        ndim_state=4,
        position=StateVector([[x], [y]]),
        rpm=20,
        fov_angle=np.radians(60),
        dwell_centre=StateVector([[0.0]]),
        resolution=Angle(np.radians(60)),
    )
    radar.timestamp = T0
    return radar


def _configs(manager, timestamp):
    """Every configuration, in the order ``BruteForceSensorManager`` enumerates them."""
    choices = {a: list(itertools.product(*a.actions(timestamp))) for a in manager.actionables}
    return [
        dict(zip(choices, combo, strict=True)) for combo in itertools.product(*choices.values())
    ]


def _key(config):
    """A configuration as comparable values (each call of ``actions`` makes new objects)."""
    return {s: tuple(float(a.target_value) for a in actions) for s, actions in config.items()}


# --------------------------------------------------------------------------------------------
# (a) the README's script
# --------------------------------------------------------------------------------------------


def test_brute_force_manager_with_the_covariance_control_reward():
    transition = _transition()
    truths = [
        GroundTruthPath([GroundTruthState([200.0, 5.0, 300.0, 3.0], timestamp=T0)]),
        GroundTruthPath([GroundTruthState([800.0, -4.0, 600.0, 2.0], timestamp=T0)]),
    ]
    offsets = ([15.0, 1.0, -10.0, 0.5], [-12.0, -0.5, 8.0, 1.0])
    tracks = {
        truth.id: Track(
            [
                GaussianState(
                    truth[0].state_vector + StateVector(off), np.diag([400.0, 25.0] * 2), T0
                )
            ]
        )
        for truth, off in zip(truths, offsets, strict=True)
    }
    radars = [_radar(0.0, 0.0), _radar(1000.0, 0.0), _radar(0.0, 1000.0)]
    P_d = np.diag([40.0, 40.0])  # m², over (x, y)

    # the README's snippet
    reward = CovarianceControlReward(
        predictor=KalmanPredictor(transition),
        updater=ExtendedKalmanUpdater(measurement_model=None),
        metric="frobenius",
        desired_covariance=P_d,
        state_indices=POS,
    )
    manager = BruteForceSensorManager(sensors=set(radars), reward_function=reward)

    unobserved = {k: t[-1].covar for k, t in tracks.items()}
    rewards_seen = set()
    for step in range(1, 5):
        t = T0 + step * DT
        for truth in truths:  # noise-free straight lines: the test is deterministic
            truth.append(
                GroundTruthState(transition.function(truth[-1], time_interval=DT), timestamp=t)
            )
        configs, best = manager.choose_actions(set(tracks.values()), t, return_reward=True)
        assert len(configs) == 1 and configs[0] is not None
        config = configs[0]
        assert set(config) == set(radars)
        assert all(len(actions) == 1 for actions in config.values())  # one dwell centre each

        # the oracle: every configuration scored; the manager keeps the first best one
        everything = _configs(manager, t)
        assert len(everything) == 5**3
        values = [reward(c, set(tracks.values()), t) for c in everything]
        rewards_seen.update(round(v, 6) for v in values)
        top = max(values)
        assert best[0] == top
        assert _key(config) == _key(everything[values.index(top)])
        assert reward(config, set(tracks.values()), t) == top

        # the reward's hypothetical covariances, then the real step: act, measure, update
        expected = reward.updated_covariances(config, list(tracks.values()), t)
        for radar, actions in config.items():
            radar.add_actions(actions)
            radar.act(t)
        by_truth = {truth[-1]: key for key, truth in zip(tracks, truths, strict=True)}
        predicted = {k: reward.predictor.predict(tr, timestamp=t) for k, tr in tracks.items()}
        state = dict(predicted)
        for radar in sorted(config, key=radars.index):
            for det in radar.measure(set(by_truth), noise=False):
                assert isinstance(det, TrueDetection)
                key = by_truth[det.groundtruth_path]
                state[key] = reward.updater.update(SingleHypothesis(state[key], det))
        for key, track in tracks.items():
            track.append(state[key])
            unobserved[key] = reward.predictor.predict(
                GaussianState(track[-2].state_vector, unobserved[key], track[-2].timestamp),
                timestamp=t,
            ).covar
            # the real update's covariance is the one the reward predicted (the real detections
            # differ from the predicted ones only in where the next linearisation happens)
            np.testing.assert_allclose(track.covar, expected[track], rtol=0.02, atol=1e-6)
        f_now = sum(reward.track_cost(tr, tr.covar, t) for tr in tracks.values())
        assert -f_now == pytest.approx(top, rel=0.02)

    assert len(rewards_seen) > 3  # the configurations do differ, the choice is not a tie
    for key, track in tracks.items():  # observed as the objective asks: far below no sensing
        pos = np.ix_(POS, POS)
        assert np.trace(track.covar[pos]) < 0.5 * np.trace(unobserved[key][pos])
        assert METRICS["frobenius"](np.asarray(track.covar[pos]), P_d) < 40.0


# --------------------------------------------------------------------------------------------
# (b) the value by hand, linear-Gaussian sensors
# --------------------------------------------------------------------------------------------


class LinearSensor(SimpleSensor):
    """A linear-Gaussian Stone Soup sensor without actions that detects every target."""

    model: LinearGaussian = Property(doc="measurement model")

    @property
    def measurement_model(self):
        return self.model

    def is_detectable(self, state, measurement_model=None):
        return True

    def is_clutter_detectable(self, state):
        return True


def _linear_case(seed):
    rng = np.random.default_rng(seed)
    tracks = []
    for _ in range(2):
        A = rng.normal(size=(4, 4))
        P0 = A @ A.T * 30.0 + np.diag([300.0, 10.0, 300.0, 10.0])
        tracks.append(Track([GaussianState(rng.normal(size=(4, 1)) * 100.0, P0, timestamp=T0)]))
    specs = [
        ((0, 2), np.array([[400.0, 120.0], [120.0, 90.0]])),
        ((0,), np.array([[900.0]])),
        ((1, 3), np.diag([4.0, 9.0])),
    ]
    sensors = [LinearSensor(model=LinearGaussian(4, mapping, R)) for mapping, R in specs]
    return tracks, sensors, specs


def _by_hand(P0, specs, chosen):
    """Predicted then updated covariance in information form, plain numpy."""
    F = _transition().matrix(time_interval=DT)
    Q = _transition().covar(time_interval=DT)
    P = F @ P0 @ F.T + Q
    info = np.linalg.inv(P)
    for j in chosen:
        mapping, R = specs[j]
        H = np.zeros((len(mapping), 4))
        H[np.arange(len(mapping)), list(mapping)] = 1.0
        info = info + H.T @ np.linalg.inv(R) @ H
    return np.linalg.inv(info)


_HAND = {
    "frobenius": lambda A, B: np.linalg.norm(A - B, "fro"),
    "spectral": lambda A, B: np.linalg.norm(A - B, 2),
    "abs_trace": lambda A, B: np.abs(np.diag(A - B)).sum(),
    "trace_diff": lambda A, B: abs(np.trace(A) - np.trace(B)),
    "one_norm": lambda A, B: np.abs(A - B).sum(axis=0).max(),
    "logdet": lambda A, B: (
        np.linalg.slogdet((A + B) / 2)[1]
        - 0.5 * (np.linalg.slogdet(A)[1] + np.linalg.slogdet(B)[1])
    ),
    "kl": lambda A, B: (
        0.25 * (np.trace(np.linalg.solve(B, A)) + np.trace(np.linalg.solve(A, B)) - 2 * len(A))
    ),
}


@pytest.mark.parametrize("metric", sorted(_HAND))
@pytest.mark.parametrize("seed", [0, 1])
def test_reward_is_minus_the_weighted_metric_by_hand(metric, seed):
    tracks, sensors, specs = _linear_case(seed)
    desired = {
        tracks[0]: np.array([[60.0, 10.0], [10.0, 50.0]]),
        tracks[1]: np.array([[120.0, -20.0], [-20.0, 80.0]]),
    }
    weights = {tracks[0]: 1.0, tracks[1]: 2.5}
    reward = CovarianceControlReward(
        predictor=KalmanPredictor(_transition()),
        updater=ExtendedKalmanUpdater(measurement_model=None),
        metric=metric,
        desired_covariance=lambda track, time: desired[track],
        state_indices=POS,
        weight=lambda track, time: weights[track],
    )
    pos = np.ix_(POS, POS)
    for chosen in [(), (0,), (1,), (2,), (0, 1), (0, 1, 2)]:
        config = {sensors[j]: [] for j in chosen}
        hand = 0.0
        for track in tracks:
            P = _by_hand(np.asarray(track.covar), specs, chosen)[pos]
            hand -= weights[track] * _HAND[metric](P, desired[track])
        assert reward(config, set(tracks), T0 + DT) == pytest.approx(hand, rel=1e-9)


def test_one_desired_matrix_all_components_default_weight():
    tracks, sensors, specs = _linear_case(5)
    P_d = np.diag([50.0, 3.0, 60.0, 4.0])
    reward = CovarianceControlReward(
        KalmanPredictor(_transition()), ExtendedKalmanUpdater(None), "frobenius", P_d
    )
    config = {sensors[0]: [], sensors[2]: []}
    hand = -sum(
        np.linalg.norm(_by_hand(np.asarray(t.covar), specs, (0, 2)) - P_d, "fro") for t in tracks
    )
    assert reward(config, tracks, T0 + DT) == pytest.approx(hand, rel=1e-9)


# --------------------------------------------------------------------------------------------
# (c) desired = a configuration's own updated covariance: that configuration scores 0, the max
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("metric", sorted(METRICS))
def test_a_configurations_own_covariance_as_desired_scores_the_maximum_zero(metric):
    track = Track([GaussianState([200.0, 5.0, 300.0, 3.0], np.diag([400.0, 25.0] * 2), T0)])
    radars = [_radar(0.0, 0.0), _radar(1000.0, 0.0)]
    t = T0 + DT
    probe = CovarianceControlReward(
        KalmanPredictor(_transition()),
        ExtendedKalmanUpdater(None),
        metric,
        np.eye(2),
        state_indices=POS,
    )
    manager = BruteForceSensorManager(sensors=set(radars), reward_function=probe)
    configs = _configs(manager, t)
    covars = [probe.updated_covariances(c, [track], t)[track][np.ix_(POS, POS)] for c in configs]
    traces = [np.trace(P) for P in covars]
    # a configuration in which both radars see the target (the smallest covariance)
    target = int(np.argmin(traces))
    assert traces[target] < min(t for t in traces if t > traces[target] * 1.01) / 1.01
    reward = CovarianceControlReward(
        KalmanPredictor(_transition()),
        ExtendedKalmanUpdater(None),
        metric,
        covars[target],
        state_indices=POS,
    )
    values = [reward(c, {track}, t) for c in configs]
    assert values[target] == pytest.approx(0.0, abs=1e-9)
    assert values[target] >= max(values) - 1e-9
    _, best = BruteForceSensorManager(sensors=set(radars), reward_function=reward).choose_actions(
        {track}, t, return_reward=True
    )
    assert best[0] == pytest.approx(0.0, abs=1e-9)


# --------------------------------------------------------------------------------------------
# a user's mistakes
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"metric": "nope"}, "unknown metric 'nope'; valid metrics: abs_trace"),
        ({"desired_covariance": np.eye(3)}, "desired_covariance is 3x3 but state_indices"),
        ({"desired_covariance": [1.0, 2.0]}, "must be a square matrix"),
        ({"state_indices": (0, 0)}, "state_indices must be distinct"),
        ({"weight": -1.0}, "weight must be a finite number >= 0"),
        # accepted, then numpy's LinAlgError at the first call (kl, logdet), or symmetrised
        ({"desired_covariance": -np.eye(2)}, "desired_covariance is not positive definite"),
        ({"desired_covariance": np.zeros((2, 2))}, "desired_covariance is not positive definite"),
        ({"desired_covariance": [[1.0, 0.5], [0.0, 1.0]]}, "desired_covariance is not symmetric"),
    ],
)
def test_bad_parameters_are_refused_naming_them(kwargs, match):
    args = {
        "predictor": KalmanPredictor(_transition()),
        "updater": ExtendedKalmanUpdater(None),
        "metric": "frobenius",
        "desired_covariance": np.eye(2),
        "state_indices": POS,
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        CovarianceControlReward(**args)
