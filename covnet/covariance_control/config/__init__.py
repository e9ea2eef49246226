"""The ``covariance_control`` kind's config (``configs/paper.yaml``, ``configs/latency.yaml``,
``configs/multitarget.yaml``): YAML -> validated, frozen records; every problem reported with
its path.

A file without a top-level ``kind`` is of this kind.  :func:`from_dict` runs the shared loader
pipeline (:func:`covnet.config.validate`: security paths resolved, the structure validated,
then the checks below and the network table's, every problem with its path):
unique sensor ids, the desired-covariance schedule, allocation constraints, metric names,
fusion modes by the fusion-rule registry (:data:`~covnet.covariance_control.fusion_rules.
FUSION_RULES`), the peer graph.

**Many targets** (spec ``multitarget.md``): a config that lists ``targets:`` (each with its
initial state, optional truth ``manoeuvres``, its own ``desired`` schedule and ``weight``)
replaces the one ``target:`` and the top-level ``desired:``; its sensors may then be of any
``model:`` of the registry (:data:`covnet.core.sensor_models.SENSOR_MODELS`: ``position``, the
default and the paper's; ``range_bearing``; ``bearing``; any model registered there), each
with its model's own keys (its noise parameters, validated by the record of the model's
``config_fields``: :func:`fields_record`), a ``position_m``, coverage (``max_range_m``,
``fov``), ``pd`` and ``clutter_rate``; the ``association`` table (``pda`` | ``nearest``, gate,
clutter window) and ``ospa`` (cut-off and order) go with it.  A config without ``targets:``
is the paper's linear one-target scenario and takes none of these (so its normalised form and
hash are what they were).  A sensor that can never cover any target (on the targets'
noise-free trajectories) is a :class:`ConfigWarning`, not an error.

The package holds one module per part of the schema, and this one the loader (:func:`from_dict`,
:func:`load`, :func:`normalised`, :func:`config_hash`) and every name of them:
:mod:`~.scenario` (the whole :class:`Scenario`, the sweep grid), :mod:`~.sensors` (a sensor,
its model's keys, its coverage), :mod:`~.targets` (the one target or many, the filter, the
desired schedules, association, OSPA), :mod:`~.allocation`, :mod:`~.fusion` (its tables),
:mod:`~.fields` (the shared field types) and :mod:`~.checks` (the checks across records, with
their messages, and the coverage warning).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from covnet.config import ConfigWarning as ConfigWarning
from covnet.config import hash_of, read_yaml, validate, warn_config
from covnet.config import normalised as _normalised
from covnet.covariance_control.config.allocation import AUTO_NODE_LIMIT as AUTO_NODE_LIMIT
from covnet.covariance_control.config.allocation import BOUNDED_GAP as BOUNDED_GAP
from covnet.covariance_control.config.allocation import AllocationSpec as AllocationSpec
from covnet.covariance_control.config.checks import (
    MULTITARGET_MAX_SENSORS as MULTITARGET_MAX_SENSORS,
)
from covnet.covariance_control.config.checks import nominal_positions as nominal_positions
from covnet.covariance_control.config.checks import reach_warnings as reach_warnings
from covnet.covariance_control.config.checks import semantic_problems as _semantic_problems
from covnet.covariance_control.config.fields import FusionMode as FusionMode
from covnet.covariance_control.config.fields import FusionRuleName as FusionRuleName
from covnet.covariance_control.config.fields import MetricName as MetricName
from covnet.covariance_control.config.fields import SearchName as SearchName
from covnet.covariance_control.config.fields import SensorModelName as SensorModelName
from covnet.covariance_control.config.fields import TrackRule as TrackRule
from covnet.covariance_control.config.fusion import PEER_GRAPHS as PEER_GRAPHS
from covnet.covariance_control.config.fusion import FusionSpec as FusionSpec
from covnet.covariance_control.config.fusion import PeerSpec as PeerSpec
from covnet.covariance_control.config.scenario import Scenario as Scenario
from covnet.covariance_control.config.scenario import SweepSpec as SweepSpec
from covnet.covariance_control.config.sensors import _SENSOR_EXTRAS
from covnet.covariance_control.config.sensors import FovSpec as FovSpec
from covnet.covariance_control.config.sensors import SensorSpec as SensorSpec
from covnet.covariance_control.config.sensors import fields_record as fields_record
from covnet.covariance_control.config.sensors import in_coverage as in_coverage
from covnet.covariance_control.config.targets import AssociationSpec as AssociationSpec
from covnet.covariance_control.config.targets import DesiredSpec as DesiredSpec
from covnet.covariance_control.config.targets import FilterSpec as FilterSpec
from covnet.covariance_control.config.targets import ManoeuvreSpec as ManoeuvreSpec
from covnet.covariance_control.config.targets import OspaSpec as OspaSpec
from covnet.covariance_control.config.targets import TargetDesiredSpec as TargetDesiredSpec
from covnet.covariance_control.config.targets import TargetEntry as TargetEntry
from covnet.covariance_control.config.targets import TargetSpec as TargetSpec
from covnet.covariance_control.config.targets import segments as segments
from covnet.covariance_control.searches import AUTO_EXACT_MAX as AUTO_EXACT_MAX
from covnet.covariance_control.searches import BOUNDED_OPTIONS as BOUNDED_OPTIONS

__all__ = [
    "KIND",
    "AssociationSpec",
    "ConfigWarning",
    "FovSpec",
    "FusionSpec",
    "ManoeuvreSpec",
    "OspaSpec",
    "TargetEntry",
    "PeerSpec",
    "Scenario",
    "SensorSpec",
    "SweepSpec",
    "config_hash",
    "older_hashes",
    "from_dict",
    "load",
    "normalised",
    "with_overrides",
]

KIND = "covariance_control"


def from_dict(data: object, source: str = "<dict>", base_dir: str | Path | None = None) -> Scenario:
    """Validate a parsed config mapping; raise :class:`ConfigError` listing every problem.

    ``base_dir``: relative paths under ``network.security`` are resolved against it (:func:`load`
    passes the config file's directory); without it they stay relative to the working directory.
    A sensor that never covers any target is a :class:`ConfigWarning` (:func:`reach_warnings`).
    """
    sc = validate(Scenario, data, source, base_dir, _semantic_problems)
    for path, message in reach_warnings(sc):
        warn_config(path, message)  # at every load, pointed at the caller's line
    return sc


def load(path: str | Path) -> Scenario:
    """Read and validate a YAML scenario file (:func:`covnet.kinds.load` reads any kind)."""
    p = Path(path)
    return from_dict(read_yaml(p), str(p), base_dir=p.parent)


_PAPER_OMITS = (
    "network.security",
    "surveillance",
    "targets",
    "association",
    "ospa",
    "allocation.detection",
    "allocation.max_per_target",
)


def normalised(sc: Scenario) -> dict[str, Any]:
    """The config with every default filled in, as plain JSON-able data (except
    ``network.security`` while it is all off, ``evaluation`` while it is the default and the
    allocation fields added later while at their defaults, so that configs without them keep
    their hash).  ``allocation.required`` and ``allocation.excluded`` are sets: they are
    listed in the order of ``sensors:``, however the file wrote them, so that one config has
    one hash (:func:`older_hashes` gives the hash covnet gave it before).

    A config without ``targets:`` leaves out every key the many-target scenario added (they
    hold their defaults: the semantic checks see to it), so that its hash is what it was; one
    with ``targets:`` leaves out the one-target ``target`` and ``desired`` it does not use, and
    says ``network.latency.missed_command: off``, what it does."""
    return _in_sensor_order(_as_written(sc))


def _in_sensor_order(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` (a normalised config) with ``allocation.required`` and ``excluded`` in the
    order of its ``sensors:`` (an id of no sensor, which the checks refuse, last)."""
    order = {s["id"]: i for i, s in enumerate(data["sensors"])}
    allocation = data["allocation"]
    for key in ("required", "excluded"):
        allocation[key] = sorted(allocation[key], key=lambda sid: order.get(sid, len(order)))
    return data


def older_hashes(sc: Scenario) -> tuple[str, ...]:
    """The config hashes covnet gave ``sc`` before :func:`normalised` put ``required`` and
    ``excluded`` in the order of ``sensors:`` (they hashed the lists as written), where they
    differ from :func:`config_hash`: a run directory or recording made then is still this
    config's (``covnet plot``, ``export``, ``replay``)."""
    h = hash_of(_as_written(sc))
    return () if h == config_hash(sc) else (h,)


def _as_written(sc: Scenario) -> dict[str, Any]:
    """:func:`normalised` with ``required`` and ``excluded`` as the file lists them."""
    later = ("evaluation", *(f"allocation.{f}" for f in _ADDED))
    if sc.sweep is not None:  # the surveillance grid, added later: left out while unset
        later = (*later, "sweep.search_weight")
    if not sc.multitarget:
        data = _normalised(sc, (*_PAPER_OMITS, *later))
        for s in data["sensors"]:
            for key in (*_SENSOR_EXTRAS, "sigma_range_m", "sigma_bearing_mrad"):
                s.pop(key, None)
        return data
    data = _normalised(sc, ("network.security", *later))
    del data["target"], data["desired"]
    if sc.surveillance is None:  # the surveillance keys (added later) leave the hash as it was
        del data["surveillance"]
        for t in data["targets"]:
            for key in ("appears_at_scan", "leaves_at_scan", "cued"):
                t.pop(key, None)
    # with targets a missed command is always a scan off (the only choice: see the checks)
    data["network"]["latency"]["missed_command"] = "off"
    return data


#: allocation fields added after configs were first hashed (left out while at their default)
_ADDED = ("search", *BOUNDED_OPTIONS, "policy", "budget")


def config_hash(sc: Scenario) -> str:
    """SHA-256 (first 16 hex digits) of the normalised config as canonical JSON."""
    return hash_of(normalised(sc))


def with_overrides(sc: Scenario, **changes: Any) -> Scenario:
    """A copy of ``sc`` with top-level fields replaced, re-validated."""
    data = normalised(sc)
    data.update(changes)
    return from_dict(data, f"{sc.name} (with overrides)")
