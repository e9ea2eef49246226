"""Scenario configuration: YAML -> validated, frozen records; every problem reported with its path.

``load(path)`` parses YAML (``yaml.safe_load``), validates the structure with pydantic (unknown keys
are errors: they are usually typos), then runs the semantic checks that span several fields
(unique sensor ids, the desired-covariance schedule, allocation constraints, metric names).  All
problems of one stage are collected and raised together as one :class:`ConfigError` whose lines
read ``sensors[3].rho: must be in (-1, 1)``.

The YAML is the single source of truth for a run; :func:`config_hash` stamps it into every result.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    ValidationError,
    field_validator,
    model_validator,
)

__all__ = [
    "ConfigError",
    "FusionSpec",
    "PeerSpec",
    "Scenario",
    "SecuritySpec",
    "SensorSpec",
    "TlsSpec",
    "config_hash",
    "load",
    "from_dict",
]


# Scalars are strict (no "0.5" strings, no booleans as numbers); lists become tuples.
Float = Annotated[float, Strict()]
Int = Annotated[int, Strict()]
Str = Annotated[str, Strict()]
Bool = Annotated[bool, Strict()]
Pair = Annotated[tuple[Float, ...], Field(min_length=2, max_length=2)]
Quad = Annotated[tuple[Float, ...], Field(min_length=4, max_length=4)]


class ConfigError(ValueError):
    """A configuration problem; ``problems`` holds ``(path, message)`` pairs, all of them."""

    def __init__(self, source: str, problems: Sequence[tuple[str, str]]):
        self.source = source
        self.problems = list(problems)
        lines = [f"{path}: {msg}" if path else msg for path, msg in self.problems]
        super().__init__(f"invalid config {source}:\n  " + "\n  ".join(lines))


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _positive(v: float) -> float:
    if not v > 0:
        raise ValueError(f"must be > 0, got {v}")
    return v


class SensorSpec(_Model):
    """A linear position sensor: ``R = [[σx², ρσxσy], [ρσxσy, σy²]]``."""

    id: Str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    sigma_x_m: Float
    sigma_y_m: Float
    rho: Float

    _pos = field_validator("sigma_x_m", "sigma_y_m")(_positive)

    @field_validator("rho")
    @classmethod
    def _rho(cls, v: float) -> float:
        if not -1.0 < v < 1.0:
            raise ValueError(f"must be in (-1, 1), got {v}")
        return v


class TargetSpec(_Model):
    """One constant-velocity target in the plane, state ``[x, vx, y, vy]``."""

    initial_position_m: Pair = (0.0, 0.0)
    initial_velocity_mps: Pair = (426.0, 0.0)
    accel_noise_std_mps2: Float = 0.5

    @field_validator("accel_noise_std_mps2")
    @classmethod
    def _q(cls, v: float) -> float:
        if not v >= 0:
            raise ValueError(f"must be >= 0, got {v}")
        return v


class FilterSpec(_Model):
    """Filter initialisation: ``P0 = diag(P0_diag)``; the estimate is the truth plus one draw
    from ``N(0, P0)`` (``perturbed``, the default) or the truth itself (``truth``)."""

    P0_diag: Quad = (1.0e4, 1.0e2, 1.0e4, 1.0e2)
    initial_estimate: Literal["perturbed", "truth"] = "perturbed"

    @field_validator("P0_diag")
    @classmethod
    def _p0(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(d > 0 for d in v):
            raise ValueError(f"every entry must be > 0, got {list(v)}")
        return v


class DesiredSpec(_Model):
    """Desired covariance from scan ``from_scan`` on: ``diag`` (4 entries) or a full ``matrix``."""

    from_scan: Int = Field(ge=1)
    diag: Quad | None = None
    matrix: Annotated[tuple[Quad, ...], Field(min_length=4, max_length=4)] | None = None

    def as_matrix(self) -> np.ndarray:
        if self.diag is not None:
            return np.diag(np.asarray(self.diag, dtype=np.float64))
        return np.asarray(self.matrix, dtype=np.float64)


class AllocationSpec(_Model):
    """Covariance-control allocation: metrics by registry name, constraints by sensor id."""

    metrics: tuple[Str, ...] = ("spectral", "abs_trace", "svd")
    required: tuple[Str, ...] = ()
    excluded: tuple[Str, ...] = ()
    max_active: Int | None = Field(default=None, ge=1)
    tie_rtol: Float = Field(default=1e-9, ge=0.0, le=1e-3)
    account_for_loss: Bool = False


FUSION_MODES = ("central", "info", "ci", "peer")
PEER_RULES = ("info", "ci")
PEER_GRAPHS = ("full", "ring", "star", "custom")
CI_OBJECTIVES = ("det", "trace", "fast")


class PeerSpec(_Model):
    """Peer-to-peer mode: which sensors exchange local tracks (``graph``; ``custom`` takes
    undirected ``edges`` by sensor id; ``star`` has ``hub`` at its centre, default the first
    sensor) and how each node fuses what it receives (``rule``)."""

    rule: Literal["info", "ci"] = "info"
    graph: Literal["full", "ring", "star", "custom"] = "full"
    hub: Str | None = None
    edges: tuple[tuple[Str, Str], ...] = ()


class FusionSpec(_Model):
    """The fusion structure (README, "Decentralized fusion"): ``central`` (the manager fuses
    raw measurements), ``info`` / ``ci`` (sensors run local filters and publish local tracks;
    the manager fuses them by information-matrix fusion or covariance intersection), ``peer``
    (no fusion centre: nodes fuse their neighbours' tracks, see :class:`PeerSpec`).
    ``ci_objective``: what the covariance-intersection weights minimise (``det``, ``trace``)
    or ``fast`` (closed-form weights ``w_i ∝ 1 / tr P_i``)."""

    mode: Literal["central", "info", "ci", "peer"] = "central"
    ci_objective: Literal["det", "trace", "fast"] = "det"
    peer: PeerSpec = PeerSpec()

    @property
    def rule(self) -> str:
        """The track-fusion rule in effect: ``central``, ``info`` or ``ci``."""
        return self.peer.rule if self.mode == "peer" else self.mode


class TlsSpec(_Model):
    """Mutual TLS for every zenoh link (``tcp/`` endpoints become ``tls/``).

    ``ca``: the CA certificate (PEM) that signed every node's certificate; ``cert_dir``: a
    directory holding ``<node_id>.pem`` and ``<node_id>.key`` (PEM) for the nodes that run on
    this host (the node id is the certificate's common name, and ``manager.pem`` is the router's
    certificate: its subject alternative names must match the host the clients connect to).
    ``verify_name: false`` lets clients accept a router certificate issued for another name.
    """

    ca: Str = Field(min_length=1)
    cert_dir: Str = Field(min_length=1)
    verify_name: Bool = True


class SecuritySpec(_Model):
    """Zenoh's access control, user/password authentication and mutual TLS (see
    :mod:`covnet.security` for what exactly is enforced). All off by default.

    - ``access_control``: the router (the manager's session) lets each node publish only its own
      keys; needs an identity, i.e. ``credentials_file`` and/or ``tls``.
    - ``credentials_file``: lines ``user:password``, one per node id (``world``, ``recorder``,
      each sensor id); each process authenticates as its node id with the password it reads from
      the file, and the router checks them against the whole file (so a host needs only the
      lines of the nodes it runs; the manager's host needs them all). A lab measure, not a
      secret store: whoever can read the file can impersonate every node in it.
    - ``tls``: mutual TLS (:class:`TlsSpec`).

    Relative paths are resolved against the config file's directory by :func:`load`.
    """

    access_control: Bool = False
    credentials_file: Str | None = Field(default=None, min_length=1)
    tls: TlsSpec | None = None

    @property
    def authenticated(self) -> bool:
        """Does every client prove an identity (password or certificate)?"""
        return self.credentials_file is not None or self.tls is not None


class LinkConfig(_Model):
    """One direction of a link (:class:`covnet.core.delay.LinkSpec`): ``delay`` a distribution
    (``{kind: constant, value_s: 0.02}``, ``uniform`` low_s/high_s, ``normal`` mean_s/std_s,
    ``exponential`` offset_s/mean_s, ``empirical`` samples_s), ``jitter_s`` (std of an extra
    normal), ``loss`` (i.i.d. drop probability), ``reorder`` (probability a message may overtake
    earlier ones)."""

    delay: dict[Str, Any] = Field(default_factory=lambda: {"kind": "constant", "value_s": 0.0})
    jitter_s: Float = 0.0
    loss: Float = 0.0
    reorder: Float = 0.0

    @model_validator(mode="after")
    def _valid_link(self) -> LinkConfig:
        for key, value in self.delay.items():
            values = value if key == "samples_s" and isinstance(value, list | tuple) else [value]
            if key != "kind" and not all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in values
            ):
                raise ValueError(f"delay.{key} must be a number of seconds, got {value!r}")
        self.spec()  # the core's checks, with its messages naming the field
        return self

    def spec(self) -> Any:
        from covnet.core.delay import LinkSpec

        return LinkSpec.from_dict(self.model_dump())


class SensorLinks(_Model):
    """Per-sensor overrides of the default links."""

    uplink: LinkConfig | None = None
    downlink: LinkConfig | None = None


class LatencySpec(_Model):
    """The network between the sensors and the fusion node (README, "Network latency").

    ``uplink`` (sensor -> manager: measurements, local tracks) and ``downlink`` (manager ->
    sensor: commands) apply to every sensor unless ``sensors.<id>`` overrides them.  Scan ``k``
    has its deadline ``deadline_fraction * period_s`` after ``t_k`` (``network.
    deadline_fraction``); a measurement arriving after it is ``late``: re-filtered as an
    out-of-sequence measurement (``late: oosm``, up to ``oosm_depth`` scans back; older ones are
    dropped) or dropped (``late: drop``), counted either way.  A sensor whose command for scan
    ``k`` has not arrived by ``t_k`` follows ``missed_command``: ``keep_last`` (its last
    command's on/off for itself), ``off`` or ``on``.  Draws come from per-link streams of the
    seed: the same config and seed give the same arrivals."""

    uplink: LinkConfig = LinkConfig()
    downlink: LinkConfig = LinkConfig()
    sensors: dict[Str, SensorLinks] = Field(default_factory=dict)
    late: Literal["oosm", "drop"] = "oosm"
    oosm_depth: Int = Field(default=5, ge=1, le=1000)
    missed_command: Literal["keep_last", "off", "on"] = "keep_last"

    def link(self, sensor_id: str, direction: str) -> Any:
        """The :class:`~covnet.core.delay.LinkSpec` of ``sensor_id``'s ``uplink`` or
        ``downlink``."""
        own = self.sensors.get(sensor_id)
        cfg = getattr(own, direction) if own is not None else None
        return (cfg or getattr(self, direction)).spec()

    def is_ideal(self, sensor_ids: Sequence[str]) -> bool:
        return all(self.link(s, d).is_ideal for s in sensor_ids for d in ("uplink", "downlink"))


class NetworkSpec(_Model):
    """How ``covnet up`` wires the processes over zenoh (see README, "Running a network").

    The manager's session is the router (``router`` endpoint; port 0 picks a free port at
    launch); world and sensors are clients connecting to ``connect`` (default: the router
    endpoint).  Everything listens on loopback unless changed here; a network reachable from
    other hosts should turn on ``security`` (passwords and/or mutual TLS, access control).
    """

    router: Str = "tcp/127.0.0.1:0"
    connect: Str | None = None
    lease_ms: Int = Field(default=1000, ge=100, le=60_000)
    heartbeat_s: Float = 0.2
    failure_timeout_s: Float = 1.0
    ready_timeout_s: Float = 30.0
    scan_timeout_s: Float = 10.0
    deadline_fraction: Float = 0.8
    restart: Literal["never", "on-failure"] = "never"
    record: bool = True
    security: SecuritySpec = SecuritySpec()
    latency: LatencySpec = LatencySpec()

    _pos = field_validator("heartbeat_s", "failure_timeout_s", "ready_timeout_s", "scan_timeout_s")(
        _positive
    )

    @field_validator("deadline_fraction")
    @classmethod
    def _frac(cls, v: float) -> float:
        if not 0.0 < v <= 1.0:
            raise ValueError(f"must be in (0, 1], got {v}")
        return v

    @field_validator("router", "connect")
    @classmethod
    def _endpoint(cls, v: str | None) -> str | None:
        if v is not None and not re.fullmatch(r"(tcp|udp|tls|quic)/[^/\s]+:\d+", v):
            raise ValueError(f"expected a zenoh endpoint like tcp/127.0.0.1:7447, got {v!r}")
        return v


class SweepSpec(_Model):
    """The grid of ``covnet sweep`` (README, "Network latency"): every combination of the mean
    one-way delay ``delay_ms`` (both directions; distributed as ``delay_kind``: ``constant``,
    ``exponential`` with that mean, ``uniform`` on ``[0, 2 · mean]``; the same for every
    sensor: ``network.latency.sensors`` is not used), the loss probability
    ``loss`` (both directions), the fusion ``modes``, ``account_for_loss`` and the ``late``
    policy, each run with ``seeds`` seeds from the config's.  ``metric``: the allocation metric
    (default: the config's first)."""

    delay_ms: tuple[Float, ...] = (0.0, 100.0, 200.0, 400.0)
    delay_kind: Literal["constant", "exponential", "uniform"] = "exponential"
    loss: tuple[Float, ...] = (0.0, 0.1, 0.2)
    modes: tuple[Literal["central", "info", "ci"], ...] = ("central", "ci")
    account_for_loss: tuple[Bool, ...] = (False, True)
    late: tuple[Literal["oosm", "drop"], ...] = ("oosm",)
    seeds: Int = Field(default=4, ge=1, le=10_000)
    metric: Str | None = None

    @field_validator("delay_ms")
    @classmethod
    def _delays(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v or any(d < 0 for d in v):
            raise ValueError(f"give at least one delay, each >= 0 ms; got {list(v)}")
        return v

    @field_validator("loss")
    @classmethod
    def _losses(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v or any(not 0.0 <= x < 1.0 for x in v):
            raise ValueError(f"give at least one loss probability, each in [0, 1); got {list(v)}")
        return v

    @field_validator("modes", "account_for_loss", "late")
    @classmethod
    def _non_empty(cls, v: tuple[Any, ...]) -> tuple[Any, ...]:
        if not v:
            raise ValueError("give at least one value")
        return v


class Scenario(_Model):
    """A whole scenario: the paper's by default values where the source leaves them open."""

    kind: Literal["covariance_control"] = "covariance_control"
    name: Str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    seed: Int = Field(ge=0)
    scans: Int = Field(ge=1, le=1_000_000)
    period_s: Float = 1.0
    target: TargetSpec = TargetSpec()
    filter: FilterSpec = FilterSpec()
    sensors: tuple[SensorSpec, ...] = Field(min_length=1)
    desired: tuple[DesiredSpec, ...] = Field(min_length=1)
    allocation: AllocationSpec = AllocationSpec()
    network: NetworkSpec = NetworkSpec()
    fusion: FusionSpec = FusionSpec()
    sweep: SweepSpec | None = None

    _period = field_validator("period_s")(_positive)

    @property
    def sensor_ids(self) -> tuple[str, ...]:
        return tuple(s.id for s in self.sensors)


def _fmt_loc(loc: Sequence[int | str]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def _fmt_error(err: Mapping[str, Any]) -> tuple[str, str]:
    path = _fmt_loc([p for p in err["loc"] if not (isinstance(p, str) and "[" in p)])
    kind = err["type"]
    if kind == "extra_forbidden":
        return path, "unknown key"
    if kind == "missing":
        return path, "missing required key"
    msg = str(err["msg"])
    value = err.get("input")
    if msg.startswith("Value error, "):
        return path, msg[len("Value error, ") :]
    if kind == "float_type" and isinstance(value, str) and _looks_numeric(value):
        return path, (
            f"expected a number, got the string {value!r} (YAML 1.1 reads an exponent without "
            "a sign as text: write 1.0e+4 or 10000.0)"
        )
    return path, f"{msg}, got {value!r}"


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _semantic_problems(sc: Scenario) -> list[tuple[str, str]]:
    from covnet.core.metrics import METRICS

    problems: list[tuple[str, str]] = []
    ids = sc.sensor_ids
    seen: set[str] = set()
    for i, sid in enumerate(ids):
        if sid in seen:
            problems.append((f"sensors[{i}].id", f"duplicate sensor id {sid!r}"))
        seen.add(sid)
    if sc.desired[0].from_scan != 1:
        problems.append(("desired[0].from_scan", "the first entry must start at scan 1"))
    for i, d in enumerate(sc.desired):
        if (d.diag is None) == (d.matrix is None):
            problems.append((f"desired[{i}]", "give exactly one of 'diag' or 'matrix'"))
            continue
        if d.matrix is not None and len(d.matrix) != 4:
            problems.append((f"desired[{i}].matrix", "must be 4x4"))
            continue
        M = d.as_matrix()
        if not np.allclose(M, M.T) or np.linalg.eigvalsh(0.5 * (M + M.T)).min() <= 0:
            problems.append((f"desired[{i}]", "must be symmetric positive definite"))
        if i > 0 and d.from_scan <= sc.desired[i - 1].from_scan:
            problems.append((f"desired[{i}].from_scan", "must increase along the schedule"))
    al = sc.allocation
    for i, m in enumerate(al.metrics):
        if m not in METRICS:
            problems.append(
                (f"allocation.metrics[{i}]", f"unknown metric {m!r}; choose from {sorted(METRICS)}")
            )
    if not al.metrics:
        problems.append(("allocation.metrics", "name at least one metric"))
    for field in ("required", "excluded"):
        for i, sid in enumerate(getattr(al, field)):
            if sid not in seen:
                problems.append((f"allocation.{field}[{i}]", f"no sensor with id {sid!r}"))
    both = set(al.required) & set(al.excluded)
    if both:
        problems.append(("allocation", f"sensors both required and excluded: {sorted(both)}"))
    if sc.network.failure_timeout_s <= sc.network.heartbeat_s:
        problems.append(("network.failure_timeout_s", "must be longer than network.heartbeat_s"))
    from covnet.security import security_problems

    problems += security_problems(sc.network, ids)
    problems += _peer_problems(sc.fusion.peer, ids)
    if sc.sweep is not None and sc.sweep.metric is not None and sc.sweep.metric not in METRICS:
        problems.append(
            ("sweep.metric", f"unknown metric {sc.sweep.metric!r}; choose from {sorted(METRICS)}")
        )
    for sid in sc.network.latency.sensors:
        if sid not in seen:
            problems.append((f"network.latency.sensors.{sid}", f"no sensor with id {sid!r}"))
    if set(al.excluded) >= set(ids):
        problems.append(("allocation.excluded", "excludes every sensor"))
    if al.max_active is not None:
        if al.max_active < len(set(al.required)):
            problems.append(
                ("allocation.max_active", f"smaller than the {len(al.required)} required sensors")
            )
        if al.max_active > len(ids):
            problems.append(("allocation.max_active", f"more than the {len(ids)} sensors"))
    return problems


def _peer_problems(peer: PeerSpec, ids: tuple[str, ...]) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    known = set(ids)
    if peer.hub is not None and peer.hub not in known:
        problems.append(("fusion.peer.hub", f"no sensor with id {peer.hub!r}"))
    if peer.graph == "custom" and not peer.edges:
        problems.append(("fusion.peer.edges", "a custom graph needs at least one edge"))
    if peer.graph != "custom" and peer.edges:
        problems.append(("fusion.peer.edges", "edges are only used with graph: custom"))
    for i, (a, b) in enumerate(peer.edges):
        for end, sid in enumerate((a, b)):
            if sid not in known:
                problems.append((f"fusion.peer.edges[{i}][{end}]", f"no sensor with id {sid!r}"))
        if a == b:
            problems.append((f"fusion.peer.edges[{i}]", f"a self-loop on {a!r}"))
    return problems


_SECURITY_PATHS = (("credentials_file",), ("tls", "ca"), ("tls", "cert_dir"))


def _resolve_security_paths(data: dict[str, Any], base_dir: Path) -> dict[str, Any]:
    """A copy of ``data`` whose relative ``network.security`` paths are joined to ``base_dir``
    (anything that is not a string is left for validation to report)."""
    net = data.get("network")
    sec = net.get("security") if isinstance(net, Mapping) else None
    if not isinstance(sec, Mapping):
        return data
    sec = dict(sec)
    for path in _SECURITY_PATHS:
        holder: Any = sec
        for part in path[:-1]:
            inner = holder.get(part)
            if not isinstance(inner, Mapping):
                holder = None
                break
            holder[part] = inner = dict(inner)
            holder = inner
        if holder is None:
            continue
        value = holder.get(path[-1])
        if isinstance(value, str) and value:
            p = Path(os.path.expanduser(value))
            holder[path[-1]] = str(p if p.is_absolute() else base_dir / p)
    return {**data, "network": {**net, "security": sec}}


KINDS = ("covariance_control", "mobile", "passive")


def scenario_kind(path: str | Path) -> str:
    """The top-level ``kind`` of a scenario file (``covariance_control`` when absent), so the CLI
    can route a file to its runner before validating it; unreadable files give the default and
    fail later with the loader's message."""
    try:
        data = read_yaml(path)
    except ConfigError:
        return "covariance_control"
    if isinstance(data, Mapping) and isinstance(data.get("kind"), str):
        return str(data["kind"])
    return "covariance_control"


def from_dict(data: object, source: str = "<dict>", base_dir: str | Path | None = None) -> Scenario:
    """Validate a parsed config mapping; raise :class:`ConfigError` listing every problem.

    ``base_dir``: relative paths under ``network.security`` are resolved against it (:func:`load`
    passes the config file's directory); without it they stay relative to the working directory.
    """
    if not isinstance(data, Mapping):
        raise ConfigError(source, [("", "the top level must be a mapping of keys to values")])
    data = dict(data)
    if base_dir is not None:
        data = _resolve_security_paths(data, Path(base_dir).absolute())
    try:
        sc = Scenario.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(source, [_fmt_error(e) for e in exc.errors()]) from None
    problems = _semantic_problems(sc)
    if problems:
        raise ConfigError(source, problems)
    return sc


def read_yaml(path: str | Path) -> object:
    """Parse a YAML file (``safe_load``); an unreadable file or bad YAML is a
    :class:`ConfigError` naming the line and column.  Every scenario kind's loader uses it."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(p), [("", f"cannot read file: {exc.strerror or exc}")]) from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(str(p), [("", f"not valid YAML: {where}{problem}")]) from None


def load(path: str | Path) -> Scenario:
    """Read and validate a YAML scenario file."""
    p = Path(path)
    return from_dict(read_yaml(p), str(p), base_dir=p.parent)


def normalised(sc: Scenario) -> dict[str, Any]:
    """The config with every default filled in, as plain JSON-able data (except
    ``network.security`` while it is all off, so that configs without it keep their hash)."""
    data = sc.model_dump(mode="json")
    if sc.network.security == SecuritySpec():
        del data["network"]["security"]
    return data


def hash_of(data: Mapping[str, Any]) -> str:
    """SHA-256 (first 16 hex digits) of JSON-able data as canonical JSON: every scenario kind's
    config hash."""
    blob = json.dumps(data, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def config_hash(sc: Scenario) -> str:
    """SHA-256 (first 16 hex digits) of the normalised config as canonical JSON."""
    return hash_of(normalised(sc))


def with_run_overrides(
    sc: Scenario, seed: int | None = None, fusion: str | None = None
) -> Scenario:
    """``sc`` with the command line's ``--seed`` and ``--fusion MODE`` applied (re-validated)."""
    if seed is None and fusion is None:
        return sc
    data = normalised(sc)
    if seed is not None:
        data["seed"] = seed
    if fusion is not None:
        data["fusion"] = {**data["fusion"], "mode": fusion}
    return from_dict(data, f"{sc.name} (with overrides)")


def with_overrides(sc: Scenario, **changes: Any) -> Scenario:
    """A copy of ``sc`` with top-level fields replaced, re-validated."""
    data = normalised(sc)
    data.update(changes)
    return from_dict(data, f"{sc.name} (with overrides)")
