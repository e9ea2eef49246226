"""What every scenario kind's config shares, and the one loader pipeline they all go through.

A scenario file is YAML; its top-level ``kind`` names the kind (:mod:`covnet.kinds`, default
``covariance_control``) whose record (:mod:`covnet.records`) describes the rest.  Every kind's
``from_dict`` calls :func:`validate`, so for every kind:

1. relative paths under ``network.security`` are resolved against the config file's folder;
2. the structure is validated (unknown keys are errors: they are usually typos; scalars are
   strict: no ``"0.5"`` strings, no booleans as numbers); every problem with its path;
3. the checks that span several fields run: the kind's own, then :func:`network_problems`
   (the ``network`` table: timeouts, per-sensor links, the shape of ``network.security``).

All problems are raised together as one :class:`ConfigError` whose lines read
``sensors[3].rho: must be in (-1, 1)``: when the structure has problems, the checks of stage 3
still run on the config without the refused values (:func:`_later_problems`).

The YAML is the single source of truth for a run; :func:`hash_of` of a kind's normalised config
(:func:`normalised`: every default filled in) is stamped into every result.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import re
import reprlib
import sys
import warnings
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Annotated, Any, Literal, Protocol, TypeVar, get_args

import yaml

from covnet.records import (
    MAX_MAGNITUDE,
    AfterValidator,
    Field,
    Placed,
    Record,
    ValidationError,
    field_validator,
    model_validator,
)

__all__ = [
    "Bool",
    "ConfigError",
    "ConfigWarning",
    "Float",
    "Ident",
    "Int",
    "LatencySpec",
    "NetworkSpec",
    "SecuritySpec",
    "Str",
    "TlsSpec",
    "unique_ids",
    "hash_of",
    "network_problems",
    "normalised",
    "read_yaml",
    "security_problems",
    "validate",
]


# Scalars are strict (no "0.5" strings, no booleans as numbers; covnet.records); lists become
# tuples.  The names say so where a config is declared.
Float = float
Int = int
Str = str
Bool = bool
Pair = Annotated[tuple[Float, ...], Field(min_length=2, max_length=2)]
Quad = Annotated[tuple[Float, ...], Field(min_length=4, max_length=4)]
Ident = Annotated[Str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]
"""A sensor, target or scenario id: it becomes part of zenoh keys and file names."""


def in_registry(choices: Callable[[], Collection[str]], what: str) -> AfterValidator:
    """The validator of a field that names an entry of a registry (a metric, a fusion rule, a
    solver): ``Annotated[Str, in_registry(...)]``, a string checked against ``choices()``
    (looked up when the config is validated, so an entry a user registers is accepted), in the
    same stage as the rest of the structure, so that a wrong name is reported together with
    every other problem."""

    def check(value: str) -> str:
        names = choices()
        if value not in names:
            raise ValueError(f"unknown {what} {value!r}; choose from {list(names)}")
        return value

    return AfterValidator(check)


class ConfigError(ValueError):
    """A configuration problem; ``problems`` holds ``(path, message)`` pairs, all of them."""

    def __init__(self, source: str, problems: Sequence[tuple[str, str]]):
        self.source = source
        self.problems = list(problems)
        lines = [f"{path}: {msg}" if path else msg for path, msg in self.problems]
        super().__init__(f"invalid config {source}:\n  " + "\n  ".join(lines))


class ConfigWarning(UserWarning):
    """A config that loads but is probably not what was meant (e.g. a sensor that can never
    cover any target); ``path`` names where.  The CLI prints it as ``covnet: warning: <path>:
    <message>``."""

    def __init__(self, path: str, message: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = path
        self.message = message


#: the warnings shown so far by the command or API call running in this context (a
#: ``warnings`` registry: its configs re-derived for each seed, metric or option do not say the
#: same again); None outside one: every load says it
_SHOWN: ContextVar[dict[Any, Any] | None] = ContextVar("covnet_config_warnings", default=None)


@contextmanager
def config_warnings_once() -> Iterator[None]:
    """Within this block (a command, an API call) each config warning is shown once, however
    often the config is validated again (a batch's seeds, an option applied); within an
    enclosing block, that block's."""
    token = _SHOWN.set(_SHOWN.get() if _SHOWN.get() is not None else {})
    try:
        yield
    finally:
        _SHOWN.reset(token)


def warn_config(path: str, message: str) -> None:
    """Warn of a config problem (:class:`ConfigWarning`) at every load (once within
    :func:`config_warnings_once`), pointed at the first line outside covnet that led to it
    (the caller's ``api.load(...)``, ``api.run(...)``).

    ``warnings.warn`` showed a warning once per process: its "default" action records it in
    the ``__warningregistry__`` of the module it names, so a second ``covnet check`` or
    ``api.load`` of the same config in one process said nothing.  ``warn_explicit`` with no
    registry (or the command's own) asks the filters each time and adds none of its own: a
    user's filters (``ignore``, ``error``, ``once``) still decide."""
    inside = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame = sys._getframe(1)
    while frame.f_back is not None and frame.f_code.co_filename.startswith(inside):
        frame = frame.f_back
    # (no module_globals: with them the source line is asked of the module's loader, which
    # raises for ``python -c``'s __main__)
    warnings.warn_explicit(
        ConfigWarning(path, message),
        ConfigWarning,
        frame.f_code.co_filename,
        frame.f_lineno,
        module=frame.f_globals.get("__name__"),
        registry=_SHOWN.get(),
    )


class ConfigModel(Record):
    """A part of a config: a validated, frozen record (:mod:`covnet.records`: strict types,
    unknown keys rejected, every problem with its path)."""


#: the largest Poisson rate of events a scan a config takes (false returns per dwell, clutter
#: per scan, births per scan): every event is drawn and processed at every scan, so a rate of
#: 1e14 tried to allocate petabytes
MAX_RATE = 1e4


def rate(v: float) -> float:
    """A field validator: a Poisson rate of events a scan, ``0 <= v <= MAX_RATE``."""
    if not v >= 0.0:
        raise ValueError(f"must be >= 0 (events a scan), got {v}")
    if v > MAX_RATE:
        raise ValueError(f"at most {MAX_RATE:g} events a scan, got {v:g}")
    return v


def positive(v: float) -> float:
    """A field validator: ``v > 0``."""
    if not v > 0:
        raise ValueError(f"must be > 0, got {v}")
    return v


def non_negative(v: float) -> float:
    """A field validator: ``v >= 0``."""
    if not v >= 0:
        raise ValueError(f"must be >= 0, got {v}")
    return v


# --------------------------------------------------------------------------------------------
# the network table (covnet up), the same for every kind
# --------------------------------------------------------------------------------------------


class TlsSpec(ConfigModel):
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


class SecuritySpec(ConfigModel):
    """Zenoh's access control, user/password authentication and mutual TLS (see
    :mod:`covnet.wire.security` for what exactly is enforced). All off by default.

    - ``access_control``: the router (the manager's session) lets each node publish only its own
      keys; needs an identity, i.e. ``credentials_file`` and/or ``tls``.
    - ``credentials_file``: lines ``user:password``, one per node id (``world``, ``recorder``,
      each sensor id); each process authenticates as its node id with the password it reads from
      the file, and the router checks them against the whole file (so a host needs only the
      lines of the nodes it runs; the manager's host needs them all). A lab measure, not a
      secret store: whoever can read the file can impersonate every node in it.
    - ``tls``: mutual TLS (:class:`TlsSpec`).

    Relative paths are resolved against the config file's directory by :func:`validate`.
    """

    access_control: Bool = False
    credentials_file: Str | None = Field(default=None, min_length=1)
    tls: TlsSpec | None = None

    @property
    def authenticated(self) -> bool:
        """Does every client prove an identity (password or certificate)?"""
        return self.credentials_file is not None or self.tls is not None


class LinkConfig(ConfigModel):
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
        if "kind" not in self.delay:
            # start-up: the link model only for configs with links (as in spec below)
            from covnet.core.delay import KINDS

            raise ValueError(f"delay.kind is required: one of {', '.join(KINDS)}")
        for key, value in self.delay.items():
            values = value if key == "samples_s" and isinstance(value, list | tuple) else [value]
            if key != "kind" and not all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in values
            ):
                raise ValueError(f"delay.{key} must be a number of seconds, got {_short(value)}")
            if key != "kind" and not all(abs(v) <= MAX_MAGNITUDE for v in values):
                # (an int beyond a float's range ended in the core's OverflowError)
                raise ValueError(
                    f"delay.{key} must be a number of seconds of magnitude at most "
                    f"{MAX_MAGNITUDE:g}, got {_short(value)}"
                )
        # the core's checks, with its messages naming the field; then the table as the core
        # reads it (floats, every parameter of the kind): written as 1 or 1.0, with a default
        # written out or left out, one config, one hash (the table was kept as written)
        # (a record check sees the record as it is built, before anyone else: it may set it)
        self.__dict__["delay"] = self.spec().delay.to_dict()
        return self

    def spec(self) -> Any:
        # imported here, not at the top: the link model is needed only by configs with links,
        # and every node process loads a config (start-up time)
        from covnet.core.delay import LinkSpec

        return LinkSpec.from_dict(self.model_dump())


class SensorLinks(ConfigModel):
    """Per-sensor overrides of the default links."""

    uplink: LinkConfig | None = None
    downlink: LinkConfig | None = None


def _missed_command(v: Any) -> str:
    """``keep_last``, ``off`` or ``on``; ``off`` and ``on`` also as YAML 1.1 reads them
    unquoted, false and true (the README's ``missed_command: off`` was refused as ``got
    False``)."""
    v = {False: "off", True: "on"}[v] if isinstance(v, bool) else v
    if not isinstance(v, str) or v not in ("keep_last", "off", "on"):
        raise ValueError(f"Input should be 'keep_last', 'off' or 'on', got {v!r}")
    return v


MissedCommand = Annotated[Any, AfterValidator(_missed_command)]


class LatencySpec(ConfigModel):
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
    missed_command: MissedCommand = "keep_last"

    def link(self, sensor_id: str, direction: str) -> Any:
        """The :class:`~covnet.core.delay.LinkSpec` of ``sensor_id``'s ``uplink`` or
        ``downlink``."""
        own = self.sensors.get(sensor_id)
        cfg = getattr(own, direction) if own is not None else None
        return (cfg or getattr(self, direction)).spec()

    def is_ideal(self, sensor_ids: Sequence[str]) -> bool:
        """Every link of ``sensor_ids`` is ideal (each default link's spec built once: this is
        asked at every run's start)."""
        default: dict[str, bool] = {}
        for s in sensor_ids:
            own = self.sensors.get(s)
            for d in ("uplink", "downlink"):
                cfg = getattr(own, d) if own is not None else None
                if cfg is not None:
                    ideal = cfg.spec().is_ideal
                elif d in default:
                    ideal = default[d]
                else:
                    ideal = default[d] = getattr(self, d).spec().is_ideal
                if not ideal:
                    return False
        return True


class EvaluationSpec(ConfigModel):
    """How the batch commands (``covnet sweep``, ``compare``, ``mc``) summarise a run's errors:
    the first ``burn_in_scans`` scans are the transient (the filter leaving its prior; on a slow
    network the first deadlines with nothing arrived yet), reported on their own; the RMSE and
    NEES *after* them are the steady state.  Default 10: the NEES has always skipped 10 scans,
    and the latency sweep's per-scan curves settle within them (README, "Network latency")."""

    burn_in_scans: Int = Field(default=10, ge=0, le=1_000_000)


class NetworkSpec(ConfigModel):
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
    record: Bool = True
    security: SecuritySpec = SecuritySpec()
    latency: LatencySpec = LatencySpec()

    _pos = field_validator("heartbeat_s", "failure_timeout_s", "ready_timeout_s", "scan_timeout_s")(
        positive
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
        problem = None if v is None else endpoint_problem(v)
        if problem is not None:
            raise ValueError(problem)
        return v


def scheduler_problem(address: str, timeout_s: float = 5.0) -> str | None:
    """What is wrong with a ``--cluster`` address, found at once (None: nothing found).  Its
    form is ``scheme://host:port``; for ``tcp://`` a plain TCP connection is tried, and a
    refused one or a host that does not resolve is a problem now, before a batch directory is
    made (Dask's client would retry a refused connection for its whole timeout).  A connection
    that only times out, and other schemes, are left to Dask's client.  No dask import here."""
    scheme, sep, rest = address.partition("://")
    host, _, port = rest.rpartition(":")
    if not sep or not scheme or not host or not port.isdigit():
        return "expected a Dask scheduler address like tcp://127.0.0.1:8786"
    if scheme != "tcp":
        return None
    import socket  # start-up: only for --cluster

    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return None
    except (ConnectionRefusedError, socket.gaierror) as exc:
        return f"cannot reach a Dask scheduler there ({exc})"
    except OSError:
        return None


def endpoint_problem(endpoint: str) -> str | None:
    """Why ``endpoint`` is not a zenoh endpoint covnet can use (None: it is):
    ``<tcp|udp|tls|quic>/<host>:<port>``, the port 0..65535."""
    m = re.fullmatch(r"(tcp|udp|tls|quic)/([^/\s]+):(\d+)", endpoint)
    if m is None:
        return f"expected a zenoh endpoint like tcp/127.0.0.1:7447, got {endpoint!r}"
    if not 0 <= int(m.group(3)) <= 65535:
        return f"the port must be in 0..65535, got {m.group(3)} in {endpoint!r}"
    return None


class Networked(Protocol):
    """What every kind's config has: the part :func:`network_problems` checks."""

    @property
    def network(self) -> NetworkSpec: ...

    @property
    def sensor_ids(self) -> tuple[str, ...]: ...


_SEC = "network.security"


def endpoint_security_problem(endpoint: str, net: NetworkSpec) -> str | None:
    """Why ``endpoint`` cannot carry this network's security (None: it can): with TLS only a
    ``tcp/`` (made ``tls/``) or ``tls/`` endpoint, without it no ``tls/``.  For the config's
    endpoints and for those given on the command line (``--router``, ``--listen``,
    ``--connect``: a ``udp/`` one there ran the whole network without TLS)."""
    proto = endpoint.partition("/")[0]
    if net.security.tls is not None and proto not in ("tcp", "tls"):
        return f"with {_SEC}.tls use a tcp/ or tls/ endpoint, got {endpoint!r}"
    if net.security.tls is None and proto == "tls":
        return f"a tls/ endpoint needs {_SEC}.tls"
    return None


def security_problems(net: NetworkSpec, sensor_ids: Sequence[str]) -> list[tuple[str, str]]:
    """``(path, message)`` for every problem in the *shape* of ``network.security`` and the
    endpoints it governs (empty when all is well). Files are not looked at here, so that a
    run directory's config stays readable where the keys are gone (``covnet run``, replay):
    :func:`covnet.wire.security.file_problems` checks them when a process starts and before
    ``covnet up`` starts any (:func:`covnet.wire.security.preflight`)."""
    sec = net.security
    problems: list[tuple[str, str]] = []
    for field in ("router", "connect"):
        ep = getattr(net, field)
        if ep is not None and (problem := endpoint_security_problem(ep, net)) is not None:
            problems.append((f"network.{field}", problem))
    if sec.access_control and not sec.authenticated:
        problems.append(
            (
                f"{_SEC}.access_control",
                f"needs node identities: set {_SEC}.credentials_file and/or {_SEC}.tls",
            )
        )
    # the manager's, world's and recorder's ids name their processes, keys and (with
    # security) identities: a sensor of that name passed check and run, and covnet up failed
    # with a traceback ("duplicate process names")
    reserved = ("manager", "world", "recorder")  # covnet.wire.keys.RESERVED_IDS (start-up)
    for i, sid in enumerate(sensor_ids):
        if sid in reserved:
            problems.append(
                (
                    f"sensors[{i}].id",
                    f"{sid!r} is the name of one of the network's own nodes "
                    f"({', '.join(reserved)}): give the sensor another id",
                )
            )
    return problems


def network_problems(cfg: Networked) -> list[tuple[str, str]]:
    """The checks of the ``network`` table that span fields, for every kind: the failure timeout
    against the heartbeat, per-sensor links naming known sensors, the shape of
    ``network.security`` (:func:`security_problems`)."""
    net, ids = cfg.network, cfg.sensor_ids
    problems: list[tuple[str, str]] = []
    if net.failure_timeout_s <= net.heartbeat_s:
        problems.append(("network.failure_timeout_s", "must be longer than network.heartbeat_s"))
    for sid in net.latency.sensors:
        if sid not in ids:
            problems.append((f"network.latency.sensors.{sid}", f"no sensor with id {sid!r}"))
    return problems + security_problems(net, ids)


def unique_ids(noun: str) -> AfterValidator:
    """The validator of a table of records with an ``id`` (sensors, targets):
    ``Annotated[tuple[Spec, ...], unique_ids("sensor")]``, run with the structure (so a repeated
    id is reported together with every other problem) at ``<table>[i].id``, type
    ``duplicate_id`` (the loader's repair renames that record: :func:`_repaired`)."""

    def check(records: tuple[Any, ...]) -> tuple[Any, ...]:
        seen: set[str] = set()
        for i, r in enumerate(records):
            if r.id in seen:
                raise Placed((i, "id"), f"duplicate {noun} id {r.id!r}", "duplicate_id")
            seen.add(r.id)
        return records

    return AfterValidator(check)


# --------------------------------------------------------------------------------------------
# the loader pipeline
# --------------------------------------------------------------------------------------------


def _fmt_loc(loc: Sequence[int | str]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def _fmt_error(err: Mapping[str, Any]) -> tuple[str, str]:
    path = _fmt_loc(err["loc"])
    kind = err["type"]
    if kind == "extra_forbidden":
        return path, "unknown key"
    if kind == "missing":
        return path, "missing required key"
    msg = str(err["msg"])
    value = err.get("input")
    if kind in ("value_error", "duplicate_id"):
        return path, msg
    if (
        kind in ("int_type", "float_type")
        and isinstance(value, str)
        and _YAML11_NUMBER.fullmatch(value.strip())
    ):
        try:
            read = yaml.safe_load(value)  # what YAML 1.1 makes of it (a plain string: safe)
        except yaml.YAMLError:
            read = None
        if isinstance(read, (int, float)) and not isinstance(read, bool):
            return path, (
                f"expected a number in plain decimal form, got {value!r}, which YAML 1.1 "
                f"reads as {read!r} (octal, base 60, hexadecimal, binary or with '_'): write "
                "the number you mean in decimal"
            )
    if kind == "float_type" and isinstance(value, str) and _looks_numeric(value):
        if (m := _EXPONENT.fullmatch(value.strip())) and not _YAML_FLOAT.fullmatch(value.strip()):
            mantissa, exponent = m.group(1), m.group(2)
            mantissa += "" if "." in mantissa else ".0"
            exponent = exponent if exponent[0] in "+-" else "+" + exponent
            return path, (
                f"expected a number, got the string {value!r} (YAML 1.1 reads an exponent "
                "without a sign, or a number with an exponent and no dot, as text: write "
                f"{mantissa}e{exponent})"
            )
        return path, f"expected a number, got the string {value!r} (drop the quotes)"
    return path, f"{msg}, got {_short(value)}"


#: how a refused value is quoted in a message: a few items and characters of it (a value of a
#: billion items, from YAML aliases, or a 5000-character string was echoed whole)
_SHORT = reprlib.Repr()
_SHORT.maxstring = _SHORT.maxother = 80
_SHORT.maxlist = _SHORT.maxtuple = _SHORT.maxdict = 6
_SHORT.maxlevel = 3


def _short(value: object) -> str:
    return _SHORT.repr(value)


#: the most values (scalars, lists, mappings) a config may hold once YAML's aliases are
#: expanded: ``&a [*b, *b, ...]`` nine levels deep is a billion of them from a few lines
MAX_CONFIG_VALUES = 1_000_000


def _count_values(data: object, limit: int) -> int:
    """The number of values in ``data`` (each visit of a shared one counts: what a reader of
    the expanded document sees), counted up to ``limit + 1`` at most."""
    n, stack = 0, [data]
    while stack and n <= limit:
        x = stack.pop()
        n += 1
        if isinstance(x, dict):
            stack.extend(x.keys())
            stack.extend(x.values())
        elif isinstance(x, list):
            stack.extend(x)
    return n


#: a number with an exponent (mantissa, exponent)
_EXPONENT = re.compile(r"([-+]?(?:\d+\.?\d*|\.\d+))[eE]([-+]?\d+)")
#: what YAML 1.1 (PyYAML) reads as a float: a dot, and an exponent only with a sign; a
#: number-like string that is not one of these was written unquoted and read as text
#: (``1e4``, ``1.0E4``, ``1e-9``), one that is was quoted
_YAML_FLOAT = re.compile(r"[-+]?(?:\d[\d_]*)?\.[\d_]*(?:[eE][-+]\d+)?")


def _root_causes(errors: Sequence[Mapping[str, Any]]) -> list[tuple[str, str]]:
    """The problems to report, each once.  (A container's length is checked only once its
    items are valid, :mod:`covnet.records`, so a bad item is not also a wrong length.)"""
    out: list[tuple[str, str]] = []
    for path, msg in map(_fmt_error, errors):
        if (path, msg) not in out:
            out.append((path, msg))
    return out


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


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
    assert isinstance(net, Mapping)
    return {**data, "network": {**net, "security": sec}}


_INT_TAG, _FLOAT_TAG = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"
#: the numbers a config may write unquoted: plain decimal integers, and floats with a dot (an
#: exponent only with a sign, as YAML 1.1 has it: the README's ``1.0e4`` pitfall, named when
#: refused).  YAML 1.1's other forms are left text, so the strict config types refuse them
#: with the key named: ``010`` (octal: 8), ``1:00`` (base 60: 60), ``1_0.0`` (10.0), ``0x1f``,
#: ``0b11`` were read silently as those numbers
_PLAIN_INT = re.compile(r"^[-+]?(?:0|[1-9][0-9]*)$")
_PLAIN_FLOAT = re.compile(
    r"^(?:[-+]?(?:[0-9]+\.[0-9]*|\.[0-9]+)(?:[eE][-+][0-9]+)?"
    r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
)
#: a string YAML 1.1 reads as a number in one of those forms (a refusal's message says why)
_YAML11_NUMBER = re.compile(
    r"[-+]?(?:0[0-9_]+|0x[0-9a-fA-F_]+|0b[01_]+|[0-9][0-9_]*(?::[0-5]?[0-9])+(?:\.[0-9_]*)?"
    r"|[0-9_]*_[0-9_]*(?:\.[0-9_]*)?(?:[eE][-+][0-9]+)?)"
)


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that notes every key repeated in one mapping (YAML's own loader keeps
    the last one silently): ``duplicates`` holds ``(key, line, first line)``, 1-based.  Merge
    keys (``<<: *anchor``) may still be overridden by the mapping's own keys.  Numbers resolve
    in their plain decimal forms only (:data:`_PLAIN_INT`, :data:`_PLAIN_FLOAT`)."""

    yaml_implicit_resolvers = {
        first: [(tag, rx) for tag, rx in resolvers if tag not in (_INT_TAG, _FLOAT_TAG)]
        for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
    }

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self.duplicates: list[tuple[object, int, int]] = []

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        if isinstance(node, yaml.MappingNode):
            first: dict[object, int] = {}
            for key_node, _ in node.value:
                if not isinstance(key_node, yaml.ScalarNode):
                    continue
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node)
                line = key_node.start_mark.line + 1
                if key in first:
                    self.duplicates.append((key, line, first[key]))
                else:
                    first[key] = line
        return super().construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_implicit_resolver(_INT_TAG, _PLAIN_INT, list("-+0123456789"))
_UniqueKeyLoader.add_implicit_resolver(_FLOAT_TAG, _PLAIN_FLOAT, list("-+0123456789."))


def _load_yaml(text: str) -> object:
    """``yaml.safe_load`` of ``text``, refusing keys repeated in a mapping (every one of them,
    with its lines, as one :class:`ConfigError` problem each; the caller names the file)."""
    loader = _UniqueKeyLoader(text)
    try:
        data = loader.get_single_data()
    finally:
        loader.dispose()
    if loader.duplicates:
        raise _DuplicateKeys(
            [
                f"duplicate key {key!r} at line {line} (first at line {first}): a key may "
                "appear once in a mapping"
                for key, line, first in loader.duplicates
            ]
        )
    return data


class _DuplicateKeys(Exception):
    def __init__(self, messages: list[str]) -> None:
        super().__init__("; ".join(messages))
        self.messages = messages


def read_yaml(path: str | Path) -> object:
    """Parse a YAML file (``safe_load``; a key repeated in a mapping is an error, not the last
    one winning), or a JSON one (a run directory's ``config.json``: JSON is YAML, but YAML 1.1
    would read ``1e-09`` as text); an unreadable file or bad YAML (JSON) is a
    :class:`ConfigError` naming the line and column."""
    p = Path(path)
    if p.exists() and not p.is_file():  # a FIFO or a device: read forever, or until no memory
        raise ConfigError(str(p), [("", "not a regular file")])
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(p), [("", f"cannot read file: {exc.strerror or exc}")]) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(str(p), [("", f"not UTF-8 text: {exc}")]) from None
    deep = "nested too deeply (lists or mappings within each other hundreds of levels down)"
    if p.suffix == ".json":
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise ConfigError(str(p), [("", f"not valid JSON: {exc}")]) from None
        except RecursionError:
            raise ConfigError(str(p), [("", f"not valid JSON: {deep}")]) from None
        return _bounded(p, data)
    try:
        return _bounded(p, _load_yaml(text))
    except RecursionError:
        raise ConfigError(str(p), [("", f"not valid YAML: {deep}")]) from None
    except _DuplicateKeys as exc:
        raise ConfigError(str(p), [("", m) for m in exc.messages]) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(str(p), [("", f"not valid YAML: {where}{problem}")]) from None


def _bounded(p: Path, data: object) -> object:
    if _count_values(data, MAX_CONFIG_VALUES) > MAX_CONFIG_VALUES:
        raise ConfigError(
            str(p),
            [("", f"more than {MAX_CONFIG_VALUES:,} values once YAML's aliases (*name) are "
                  "expanded: not a config covnet can take")],
        )  # fmt: skip
    return data


M = TypeVar("M", bound=Record)


def validate(
    model: type[M],
    data: object,
    source: str,
    base_dir: str | Path | None,
    problems: Callable[[M], list[tuple[str, str]]],
) -> M:
    """The loader pipeline every kind's ``from_dict`` runs (module docstring): resolve the
    security paths against ``base_dir`` (none: they stay relative to the working directory),
    validate the structure with ``model``, then the kind's ``problems`` and
    :func:`network_problems`; raise one :class:`ConfigError` listing every problem."""
    if not isinstance(data, Mapping):
        raise ConfigError(source, [("", "the top level must be a mapping of keys to values")])
    data = dict(data)
    kind_field = model.model_fields["kind"]
    want = get_args(kind_field.annotation)[0]
    got = data.get("kind", None if kind_field.is_required() else kind_field.default)
    if got != want:
        raise ConfigError(
            source,
            [("kind", f"expected {want!r} (a {want} config says 'kind: {want}'), got {got!r}")],
        )
    if base_dir is not None:
        data = _resolve_security_paths(data, Path(base_dir).absolute())
    try:
        cfg = model.model_validate(data)
    except ValidationError as exc:
        found = _root_causes(exc.errors())
        raise ConfigError(source, found + _later_problems(model, data, exc, problems)) from None
    found = problems(cfg) + network_problems(cfg)
    if found:
        raise ConfigError(source, found)
    return cfg


def _at(data: Any, loc: Sequence[int | str]) -> Any:
    """``data[loc[0]][loc[1]]...``, or None where there is no such place."""
    for part in loc:
        try:
            data = data[part]
        except (KeyError, IndexError, TypeError):
            return None
    return data


def _repaired(
    data: dict[str, Any], errors: Sequence[Mapping[str, Any]]
) -> tuple[Any, list[tuple[int | str, ...]]] | None:
    """``data`` without the values ``errors`` refused (each falls back to its default), and
    the scopes they lie in; None when a refused place cannot be removed."""
    scopes: list[tuple[int | str, ...]] = []
    repaired: Any = copy.deepcopy(data)
    for err in errors:
        loc = tuple(err["loc"])
        if err["type"] == "duplicate_id":
            # a repeated id (unique_ids, at <table>[i].id): that record under a stand-in id,
            # not the whole table gone (the checks that span fields need it: "no sensor with
            # id 'S9'")
            record = _at(repaired, loc[:-1])
            if isinstance(record, dict):
                record["id"] = f"{record.get('id')}_repeated_{loc[-2]}"
                scopes.append(loc[:-1])
                continue
            loc = loc[:-2]
        while loc and isinstance(loc[-1], int):  # an item of a list of values: the list
            loc = loc[:-1]
        if not loc:
            return None
        holder = repaired
        for part in loc[:-1]:
            try:
                holder = holder[part]
            except (KeyError, IndexError, TypeError):
                return None
        if isinstance(holder, dict):
            holder.pop(loc[-1], None)
        items = [i for i, part in enumerate(loc) if isinstance(part, int)]
        scopes.append(loc[: items[-1] + 1] if items else loc)
    return repaired, scopes


def _later_problems(
    model: type[M],
    data: dict[str, Any],
    exc: ValidationError,
    problems: Callable[[M], list[tuple[str, str]]],
) -> list[tuple[str, str]]:
    """What the first look at the structure could not see, so that the whole list comes at
    once: ``data`` without the values the structure refused (each falls back to its default)
    is validated again; what that refuses (a check that runs only once every item of its list
    is valid, a duplicate id behind a bad value: three rounds of fixes for one file) is added,
    removed in turn, up to a few rounds; then the checks that span fields, on the repaired
    copy.  Nothing more once a refused value has no default (the copy lacks a required key),
    and nothing said within the record that holds a refused value (a sensor whose ``model`` is
    refused would otherwise be checked as the default model)."""
    errors = list(exc.errors())
    seen = set(_root_causes(errors))
    extra: list[tuple[str, str]] = []
    for _ in range(4):
        fixed = _repaired(data, errors)
        if fixed is None:
            return extra
        repaired, scopes = fixed
        try:
            cfg = model.model_validate(repaired)
        except ValidationError as again:
            # a key missing now is one this removed (a missing one was said at first)
            more = [e for e in again.errors() if e["type"] != "missing"]
            new = [rc for rc in _root_causes(more) if rc not in seen]
            if not new:
                return extra
            extra += new
            seen.update(new)
            errors += more
            continue
        inside = [_fmt_loc(scope) for scope in scopes]
        return extra + [
            (path, msg)
            for path, msg in problems(cfg) + network_problems(cfg)
            if not any(path == s or path.startswith((f"{s}.", f"{s}[")) for s in inside)
        ]
    return extra


def normalised(cfg: Record, omit_if_default: Sequence[str] = ()) -> dict[str, Any]:
    """``cfg`` with every default filled in, as plain JSON-able data, leaving out the fields
    named in ``omit_if_default`` (dotted paths, e.g. ``network.security``) while they hold
    their default: a kind lists there what it added after configs were first hashed, so that
    configs without it keep their hash."""
    data = cfg.model_dump(mode="json")
    for path in omit_if_default:
        *parents, leaf = path.split(".")
        owner: Any = cfg
        holder = data
        for part in parents:
            owner, holder = getattr(owner, part), holder[part]
        default = type(owner).model_fields[leaf].get_default(call_default_factory=True)
        if getattr(owner, leaf) == default:
            del holder[leaf]
    return data


def hash_of(data: Mapping[str, Any]) -> str:
    """SHA-256 (first 16 hex digits) of JSON-able data as canonical JSON: the config hash of
    every kind (of its :func:`normalised` config)."""
    blob = json.dumps(data, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]
