"""Networks of any size from the paper's sensors (issue 17): ``configs/large.yaml`` and the
configs of ``covnet bench up --sensors N,...``.

Sensor ``S<f>.<g>`` is family ``f`` (the base config's ``f``-th sensor: the paper's S1..S8) at
site ``g = 1, 2, ...``: both sigmas scaled by ``1 + 0.25 (g - 1)`` (rounded to the millimetre),
the correlation kept, so the first eight are the paper's sensors themselves and every further
eight a noisier copy of them.  (This kind's position sensors measure ``z = H x + v`` with a noise
that does not depend on where they stand: a site is its noise level.)
"""

from __future__ import annotations

from typing import Any

from covnet.covariance_control.config import Scenario, normalised

__all__ = ["SITE_STEP", "bench_config", "scaled_sensors"]

#: the sigmas grow by this fraction of the base sensor's per site
SITE_STEP = 0.25


def scaled_sensors(sc: Scenario, n_sensors: int) -> list[dict[str, Any]]:
    """The first ``n_sensors`` sensors ``S<f>.<g>`` (module docstring) of ``sc``'s sensors, site
    by site, as config entries."""
    if n_sensors < 1:
        raise ValueError(f"n_sensors must be >= 1, got {n_sensors}")
    base = sc.sensors
    out = []
    for i in range(n_sensors):
        s, g = base[i % len(base)], 1 + i // len(base)
        if s.sigma_x_m is None or s.sigma_y_m is None:  # a range/bearing sensor: no family
            raise ValueError(f"sensor {s.id}: scaled families are of position sensors")
        scale = 1.0 + SITE_STEP * (g - 1)
        out.append(
            {
                "id": f"{s.id}.{g}",
                "sigma_x_m": round(s.sigma_x_m * scale, 3),
                "sigma_y_m": round(s.sigma_y_m * scale, 3),
                "rho": s.rho,
            }
        )
    return out


def bench_config(sc: Scenario, n_sensors: int, scans: int = 100) -> dict[str, Any]:
    """The config ``covnet bench up --sensors N`` runs: ``sc`` with ``n_sensors`` scaled sensors
    (:func:`scaled_sensors`), all of them required (every scan's command enables every sensor:
    one command out, N measurements back, the pattern the zenoh probe repeats; the allocation
    itself is then trivial, and ``covnet bench search`` times it), one metric (``sc``'s first),
    ``scans`` scans, recorded as ``sc`` is."""
    data = normalised(sc)
    sensors = scaled_sensors(sc, n_sensors)
    data["name"] = f"{sc.name}-{n_sensors}"
    data["sensors"] = sensors
    data["scans"] = scans
    data["allocation"] = {
        "metrics": [sc.allocation.metrics[0]],
        "required": [s["id"] for s in sensors],
    }
    data.pop("sweep", None)
    return data
