"""covnet's covariance-control objective as a Stone Soup reward function.

Optional extra: ``pip install 'covnet[stonesoup]'`` (Stone Soup 1.9.x).  covnet never imports
this module itself; importing it without Stone Soup raises an :class:`ImportError` saying how to
install it.

:class:`CovarianceControlReward` is a Stone Soup ``RewardFunction``: Stone Soup's sensor managers
call it as ``reward(config, tracks, metric_time)`` with ``config`` a mapping of sensors (or
platforms) to the actions to evaluate, and keep the configuration of largest reward.  It scores
a configuration by how close the covariances it would give are to the desired ones, covnet's
objective ``f(P_i, P_d)`` with ``f`` from :data:`covnet.core.metrics.METRICS`::

    import numpy as np
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.sensormanager import BruteForceSensorManager
    from stonesoup.updater.kalman import ExtendedKalmanUpdater

    from covnet.interop.stonesoup import CovarianceControlReward

    reward = CovarianceControlReward(
        predictor=KalmanPredictor(transition_model),
        updater=ExtendedKalmanUpdater(measurement_model=None),
        metric="frobenius",
        desired_covariance=np.diag([40.0, 40.0]),  # m², over (x, y)
        state_indices=(0, 2),                      # of the state [x, vx, y, vy]
    )
    manager = BruteForceSensorManager(sensors=set(radars), reward_function=reward)
    config = manager.choose_actions(tracks, timestamp)[0]  # {radar: [dwell action]}
    for radar, actions in config.items():
        radar.add_actions(actions)
        radar.act(timestamp)

(tests/integration/test_stonesoup_interop.py runs this pipeline with Stone Soup's rotating
radars, whose actions are dwell centres.)
"""

from __future__ import annotations

import copy
import datetime
import math
from collections.abc import Hashable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from covnet.core.metrics import METRICS, metric_names

#: how to install what this module needs
INSTALL = "pip install 'covnet[stonesoup]'"

try:
    from stonesoup.base import Property
    from stonesoup.predictor import Predictor
    from stonesoup.sensor.sensor import Sensor
    from stonesoup.sensormanager.reward import RewardFunction
    from stonesoup.types.detection import TrueDetection
    from stonesoup.types.groundtruth import GroundTruthState
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.updater import Updater
except ImportError as exc:  # pragma: no cover - exercised in a process without Stone Soup
    raise ImportError(
        f"covnet.interop.stonesoup needs Stone Soup, an optional extra of covnet: {INSTALL} "
        f"(import failed: {exc})"
    ) from exc

__all__ = ["INSTALL", "CovarianceControlReward"]

Matrix = NDArray[np.float64]


class CovarianceControlReward(RewardFunction):
    r"""Reward of a sensor configuration: minus covnet's covariance-control objective.

    For a configuration ``c`` (sensors and their actions), the tracks ``T`` and the time ``t``
    (``metric_time``)::

        R(c) = − Σ_{τ ∈ T} w_τ · f( sym(P_τ(c)[I, I]), sym(P_d,τ) )

    - ``P_τ(c)``: track ``τ``'s covariance predicted to ``t`` by :attr:`predictor`, then updated
      by :attr:`updater` with the detection each sensor of ``c`` would make of it (no update
      from a sensor that would not detect it; ``P_τ(c)`` is the prediction when none does);
    - ``I``: :attr:`state_indices`, the state components the desired covariance refers to (all
      by default); ``P[I, I]`` is that block;
    - ``P_d,τ``: :attr:`desired_covariance`, one matrix for every track or a callable
      ``(track, metric_time) -> matrix``;
    - ``f``: the covnet metric named :attr:`metric` (``covnet.core.metrics.METRICS``),
      ``f ≥ 0`` and ``f(A, A) = 0``, so ``R ≤ 0`` and ``R = 0`` when every track gets exactly
      its desired covariance;
    - ``w_τ``: :attr:`weight` (1 by default);
    - ``sym(M) = ½(M + Mᵀ)``: the metrics take symmetric matrices, and an updater's covariance
      can be asymmetric by rounding (a symmetric ``M`` is unchanged, bit for bit).

    The hypothetical detections are built as Stone Soup's ``UncertaintyRewardFunction`` builds
    them: each actionable of the configuration is deep-copied, given its actions and made to act
    up to ``t`` (without noise); each copied sensor measures, without noise, a ground-truth state
    at the track's current mean (the prediction, or the update by the previous sensors) carrying
    the track's metadata; a true detection (not clutter) updates the track through a
    ``SingleHypothesis``.  Differences from it: the sensors are taken in the configuration's order
    (Stone Soup's reward iterates a ``set``, whose order changes from call to call), and a track
    no sensor detects counts with its predicted covariance (in an uncertainty reduction it adds
    0).  With noise-free predicted measurements the update keeps the mean, so an extended Kalman
    update linearises every sensor at the prediction and ``P_τ(c)`` does not depend on the order
    beyond rounding.  Only the covariances enter: the reward is for Gaussian (Kalman-family)
    predictors and updaters.
    """

    predictor: Predictor = Property(doc="Predicts each track to ``metric_time``.")
    updater: Updater = Property(
        doc="Updates a prediction with a hypothetical detection (e.g. "
        "``ExtendedKalmanUpdater(measurement_model=None)``: each detection's own model)."
    )
    metric: str = Property(
        doc="The covnet metric ``f``: a name in ``covnet.core.metrics.METRICS``."
    )
    desired_covariance: Any = Property(
        doc="``P_d``: a square matrix over :attr:`state_indices`, or a callable "
        "``(track, metric_time) -> matrix``."
    )
    state_indices: Sequence[int] = Property(
        default=None,
        doc="The state components ``P_d`` refers to, e.g. ``(0, 2)`` for the positions of "
        "``[x, vx, y, vy]``; default all.",
    )
    weight: Any = Property(
        default=1.0,
        doc="``w``: a number ``>= 0``, or a callable ``(track, metric_time) -> number``.",
    )

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.metric not in METRICS:
            raise ValueError(
                f"CovarianceControlReward: unknown metric {self.metric!r}; "
                f"valid metrics: {', '.join(metric_names())}"
            )
        if self.state_indices is not None:
            idx = list(self.state_indices)
            if (
                not idx
                or not all(isinstance(i, int | np.integer) and i >= 0 for i in idx)
                or len(set(idx)) != len(idx)
            ):
                raise ValueError(
                    "CovarianceControlReward: state_indices must be distinct state indices "
                    f"(non-negative integers), got {self.state_indices!r}"
                )
        if not callable(self.desired_covariance):
            size = None if self.state_indices is None else len(self.state_indices)
            _desired(self.desired_covariance, size)
        if not callable(self.weight):
            _weight(self.weight)

    def __call__(
        self,
        config: Mapping[Any, Sequence[Any]],
        tracks: Iterable[Any],
        metric_time: datetime.datetime,
        *args: Any,
        **kwargs: Any,
    ) -> float:
        """``R(config)`` (see the class): ``−Σ_τ w_τ f(P_τ[I, I], P_d,τ)`` over ``tracks``."""
        tracks = list(tracks)
        covars = self.updated_covariances(config, tracks, metric_time)
        total = 0.0
        for track in tracks:
            total += self.track_cost(track, covars[track], metric_time)
        return -total

    def updated_covariances(
        self,
        config: Mapping[Any, Sequence[Any]],
        tracks: Iterable[Any],
        metric_time: datetime.datetime,
    ) -> dict[Hashable, Matrix]:
        """Each track's covariance ``P_τ(config)`` at ``metric_time`` (the full state), as
        :meth:`__call__` computes it: predicted, then updated by the configuration's sensors."""
        memo: dict[int, Any] = {}
        sensors = []
        for actionable, actions in config.items():
            acting = copy.deepcopy(actionable, memo)
            acting.add_actions(actions)
            acting.act(metric_time, noise=False)
            if isinstance(actionable, Sensor):
                sensors.append(acting)
        states = {track: self.predictor.predict(track, timestamp=metric_time) for track in tracks}
        for sensor in sensors:
            truths = {
                GroundTruthState(
                    state.state_vector, timestamp=state.timestamp, metadata=track.metadata
                ): track
                for track, state in states.items()
            }
            detected = {
                truths[d.groundtruth_path]: d
                for d in sensor.measure(set(truths), noise=False)
                if isinstance(d, TrueDetection) and d.groundtruth_path in truths
            }
            for track, detection in detected.items():
                states[track] = self.updater.update(SingleHypothesis(states[track], detection))
        return {track: np.array(state.covar, dtype=np.float64) for track, state in states.items()}

    def track_cost(self, track: Any, covar: Matrix, metric_time: datetime.datetime) -> float:
        """``w_τ f(sym(P[I, I]), sym(P_d,τ))`` for one track's covariance ``covar``."""
        P = np.asarray(covar, dtype=np.float64)
        if self.state_indices is None:
            block = P
        else:
            idx = list(self.state_indices)
            if max(idx) >= P.shape[0]:
                raise ValueError(
                    f"CovarianceControlReward: state_indices {tuple(idx)} exceed the "
                    f"{P.shape[0]}-dimensional state"
                )
            block = P[np.ix_(idx, idx)]
        desired = self.desired_covariance
        if callable(desired):
            desired = desired(track, metric_time)
        P_d = _desired(desired, block.shape[0])
        w = _weight(self.weight(track, metric_time) if callable(self.weight) else self.weight)
        f = METRICS[self.metric](_sym(block), P_d)
        return w * float(f)


def _sym(M: Matrix) -> Matrix:
    """``½(M + Mᵀ)`` as a new C-ordered array (``M`` itself when symmetric, bit for bit)."""
    out: Matrix = np.ascontiguousarray(0.5 * (M + M.T))
    return out


def _desired(value: object, size: int | None) -> Matrix:
    """A desired covariance checked: a finite square float matrix (of ``size`` when given)."""
    try:
        M = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        M = None
    if M is None or M.ndim != 2 or M.shape[0] != M.shape[1] or not M.size:
        shape = None if M is None else M.shape
        raise ValueError(
            "CovarianceControlReward: desired_covariance must be a square matrix"
            f"{'' if size is None else f' of size {size}'} (over state_indices), got shape {shape}"
        )
    if size is not None and M.shape[0] != size:
        raise ValueError(
            f"CovarianceControlReward: desired_covariance is {M.shape[0]}x{M.shape[1]} but "
            f"state_indices select {size} state components"
        )
    if not np.isfinite(M).all():
        raise ValueError("CovarianceControlReward: desired_covariance has non-finite entries")
    scale = max(float(np.max(np.abs(M))), np.finfo(np.float64).tiny)
    if float(np.max(np.abs(M - M.T))) > 1e-12 * scale:  # it was symmetrised without a word
        raise ValueError("CovarianceControlReward: desired_covariance is not symmetric")
    try:  # -I or zeros ended in numpy's LinAlgError at the first call (kl, logdet)
        np.linalg.cholesky(_sym(M))
    except np.linalg.LinAlgError:
        raise ValueError(
            "CovarianceControlReward: desired_covariance is not positive definite (a "
            "covariance the tracks could reach)"
        ) from None
    return _sym(M)


def _weight(value: object) -> float:
    """A track's weight checked: a finite number ``>= 0``."""
    try:
        w = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        w = math.nan
    if not math.isfinite(w) or w < 0:
        raise ValueError(
            f"CovarianceControlReward: weight must be a finite number >= 0, got {value!r}"
        )
    return w
