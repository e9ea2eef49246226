"""Named, counter-based random streams: every draw comes from an explicit ``Generator``.

A stream is keyed by the run seed and a tuple of small integers, ``SeedSequence(seed,
spawn_key=key)``, so the noise of sensor ``j`` at scan ``k`` is the same whichever process draws
it, in whatever order, after whatever restart.  Domains keep the uses apart.
"""

from __future__ import annotations

import numpy as np

TRUTH = 0  #: process noise of the target trajectories
INITIAL = 1  #: the filter's initial estimate
SENSOR = 2  #: measurement noise: key (SENSOR, sensor_index, scan)
POLICY = 20  #: a stochastic allocation policy's draws: key (POLICY, scan)


def stream(seed: int, *key: int) -> np.random.Generator:
    """A fresh PCG64 generator for ``(seed, key)``; independent of every other key."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key)))


def sensor_stream(seed: int, sensor_index: int, scan: int) -> np.random.Generator:
    """The generator sensor ``sensor_index`` draws its scan-``scan`` measurement noise from."""
    return stream(seed, SENSOR, sensor_index, scan)


def policy_stream(seed: int, scan: int) -> np.random.Generator:
    """The generator a stochastic allocation policy (``random``) draws scan ``scan``'s choice
    from: the same in every process and episode, whatever was decided before."""
    return stream(seed, POLICY, scan)
