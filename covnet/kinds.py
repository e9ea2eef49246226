"""The scenario kinds: ONE registry, and the one place that decides which kind a config is.

A kind is a package (``covnet/<kind>/``) whose ``kind`` module defines ``KIND``, an object of
the :class:`Kind` protocol: its config loader, its in-process runner, its results and figures,
the commands only it has (``mc``, ``compare``, ``sweep``, ``replay``, benchmarks), and the
modules of its three process roles (``manager/<kind>.py``, ``sensors/<kind>.py``,
``world/<kind>.py``, named as strings: ``covnet`` never imports the process packages).
:data:`REGISTRY` maps a config's top-level ``kind`` (default ``covariance_control``) to that
module, imported on first use, so that a process pays only for its own kind.

Nothing outside the kinds' own packages branches on the kind: the CLI, the node processes,
the recorder and the launcher ask the registry (:func:`load`, :func:`of`) and call the kind.

Adding a kind: its package with a ``kind`` module, one line in :data:`REGISTRY`, and its three
role modules (README, "Architecture").
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Collection, Iterable, Mapping
from pathlib import Path
from typing import Any, Protocol

from covnet.config import ConfigError, hash_of, read_yaml
from covnet.core import registries
from covnet.errors import UsageError

__all__ = [
    "DEFAULT",
    "OPTIONS",
    "REGISTRY",
    "Kind",
    "apply_named_options",
    "apply_options",
    "config_hash",
    "config_hashes",
    "from_dict",
    "get",
    "load",
    "of",
]

REGISTRY: dict[str, str] = {
    "covariance_control": "covnet.covariance_control.kind",
    "mobile": "covnet.mobile.kind",
    "passive": "covnet.passive.kind",
}
"""A config's ``kind`` -> the module that defines its :class:`Kind` as ``KIND``."""
registries.ship("covnet.kinds.REGISTRY", REGISTRY)
DEFAULT = "covariance_control"
"""The kind of a config without a top-level ``kind`` (the paper's)."""

OPTIONS: dict[str, str] = {
    "seed": "--seed",
    "metric": "--metric",
    "fusion": "--fusion",
    "solver": "--solver",
}
"""The command-line options that change what a run computes.  Each is a change of the config
(so ``config.json`` and the hash say what the run used); a kind lists the ones it takes in
:attr:`Kind.options`, and the others are refused with a line that says so."""

OptionFn = Callable[[dict[str, Any], Any], None]
"""Applies one option's value to a normalised config (edits the dict in place); raises
``ValueError`` with a readable message for a value the kind does not take."""


class Kind(Protocol):
    """What a scenario kind provides (each kind's ``kind`` module defines one as ``KIND``)."""

    name: str
    """The registry key, the config's ``kind``."""
    title: str
    """For messages: "a <title> scenario" (``covariance-control``, ``mobile``, ``passive``)."""
    roles: Mapping[str, str]
    """Process role (``manager``, ``sensor``, ``world``) -> the module of its loop."""
    options: Mapping[str, OptionFn]
    """The :data:`OPTIONS` this kind takes -> how each changes the normalised config."""
    commands: Mapping[str, Callable[..., int]]
    """The optional commands this kind has (``mc``, ``compare``, ``sweep``, ``replay``,
    ``bench:<target>``) -> their implementation, called with the parsed arguments."""

    def from_dict(self, data: object, source: str, base_dir: str | Path | None) -> Any:
        """Validate a parsed config (:func:`covnet.config.validate`)."""
        ...

    def normalised(self, cfg: Any) -> dict[str, Any]:
        """The config with every default filled in, as JSON-able data (what is hashed)."""
        ...

    def older_hashes(self, cfg: Any) -> tuple[str, ...]:
        """The hashes older covnets gave ``cfg`` where its normalised form changed since
        (:func:`config_hashes`)."""
        ...

    def episodes(self, cfg: Any) -> list[str]:
        """The labels of the run's episodes, in order (the live status shows them)."""
        ...

    def run(self, cfg: Any, out: Path, *, figures: bool) -> int:
        """``covnet run``: the whole scenario in this process, into ``out``."""
        ...

    def after_up(self, cfg: Any, out: Path, *, figures: bool) -> None:
        """After ``covnet up``: figures and the printed summary from the run directory."""
        ...

    def up_problem(
        self, cfg: Any, *, realtime: bool, netns: bool, foxglove: bool = False
    ) -> str | None:
        """Why ``covnet up`` cannot run ``cfg`` with this clock, emulation or live view (None:
        it can)."""
        ...

    def restartable(self, cfg: Any) -> frozenset[str]:
        """The roles (``sensor``, ``world``, ``recorder``) whose failed process may be restarted
        under ``network.restart: on-failure``."""
        ...

    def plot(self, run_dir: Path) -> list[Path]:
        """Redraw the figures of one of this kind's run directories."""
        ...

    def tracks(self, cfg: Any, run_dir: Path) -> list[Any]:
        """``covnet export``: the truths and tracks of one of this kind's run directories,
        per episode (:class:`covnet.runs.export.Episode` s); a kind without tracks raises a
        :class:`~covnet.errors.UsageError` that says so."""
        ...

    def visual(self, cfg: Any) -> Any:
        """The kind's visual module made for ``cfg`` (``covnet/<kind>/visual.py``'s ``Visual``,
        a :class:`covnet.runs.visual.KindVisual`): one scan's messages -> what Foxglove draws."""
        ...

    def mcap_problem(self, cfg: Any) -> str | None:
        """Why ``covnet run --mcap`` cannot draw ``cfg``'s scenes (None: it can); asked before
        the run, so a refusal writes nothing."""
        ...

    def check_notes(self, cfg: Any) -> list[str]:
        """What ``covnet check`` prints (``note:`` lines, exit 0) beside a valid ``cfg`` that a
        command of the kind would still refuse (a ``sweep:`` grid ``covnet sweep`` refuses)."""
        ...

    def run_messages(self, cfg: Any, run_dir: Path) -> Iterable[Any]:
        """An in-process run directory's scans as the messages a network run would have sent
        (``covnet run --mcap`` feeds them to :meth:`visual`)."""
        ...

    def rebuild(
        self,
        cfg: Any,
        run_id: str,
        episodes: list[str],
        recording: Path,
        out: Path,
        run_info: dict[str, Any] | None = None,
    ) -> Any:
        """A network run's whole directory rebuilt from its recording alone into ``out``, with
        the manager's own code and writer (``run_info`` merged into its ``run.json``): every
        episode up to its last scan fully recorded, also when the recording was cut (a killed
        recorder or manager).  Returns the :class:`covnet.runs.replay_kit.ReplayReport` (what
        differs from what the manager recorded, notes on the recording); raises
        :class:`covnet.runs.replay_kit.ReplayError` for a run that cannot be replayed at all (peer
        mode)."""
        ...


def get(name: str) -> Kind:
    """The kind registered as ``name``; an unknown one is a :class:`ConfigError` at ``kind``."""
    module = REGISTRY.get(name)
    if module is None:
        raise ConfigError(
            "config", [("kind", f"unknown scenario kind {name!r}; choose from {list(REGISTRY)}")]
        )
    kind: Kind = importlib.import_module(module).KIND
    return kind


def of(cfg: Any) -> Kind:
    """The kind of a loaded config (every kind's config records its ``kind``)."""
    return get(str(cfg.kind))


def kind_name(data: object) -> str:
    """The ``kind`` a parsed config declares (:data:`DEFAULT` when it declares none)."""
    if isinstance(data, Mapping) and "kind" in data:
        return str(data["kind"])
    return DEFAULT


def from_dict(
    data: object, source: str = "<dict>", base_dir: str | Path | None = None
) -> tuple[Kind, Any]:
    """Validate a parsed config of any kind: ``(kind, config)``."""
    name = kind_name(data)
    if name not in REGISTRY:
        raise ConfigError(
            source, [("kind", f"unknown scenario kind {name!r}; choose from {list(REGISTRY)}")]
        )
    kind = get(name)
    return kind, kind.from_dict(data, source, base_dir)


def load(path: str | Path) -> tuple[Kind, Any]:
    """Read a scenario file once and validate it as its kind: ``(kind, config)``; relative
    paths in it are resolved against its folder."""
    p = Path(path)
    return from_dict(read_yaml(p), str(p), base_dir=p.parent)


def config_hash(cfg: Any) -> str:
    """The config hash of a config of any kind (of its normalised form)."""
    return hash_of(of(cfg).normalised(cfg))


def config_hashes(cfg: Any) -> tuple[str, ...]:
    """Every hash a run of ``cfg`` may carry: :func:`config_hash` first, then those older
    covnets gave it (``Kind.older_hashes``: a run directory or recording they made is still
    this config's)."""
    return (config_hash(cfg), *of(cfg).older_hashes(cfg))


def apply_options(
    kind: Kind, cfg: Any, source: str, *, taken: Collection[str] | None = None, **values: Any
) -> Any:
    """``cfg`` with the given :data:`OPTIONS` applied (``None`` values are not given), as a
    new validated config.  An option the kind does not take, or a value it refuses, is a
    :class:`~covnet.errors.UsageError` naming the option; ``taken``: the options the command
    takes for this kind (default: those in ``values``), which a refusal lists."""
    return apply_named_options(
        kind, cfg, source, values, OPTIONS, taken=values if taken is None else taken
    )


def _check_type(spelled: str, name: str, value: Any) -> None:
    """A run option's type, named as its caller spells it (the Python API's ``metric=3`` and
    ``seed="a"`` ended in a bare ``TypeError`` from deep inside; the command line's are typed
    by its parser): ``metric`` a list of names, ``seed`` an integer, the others names."""
    if name == "metric":
        ok = isinstance(value, list | tuple) and all(isinstance(m, str) for m in value)
        want = "a metric name or a list of them"
    elif name == "seed":
        ok = isinstance(value, int) and not isinstance(value, bool)
        want = "an integer"
    else:
        ok = isinstance(value, str)
        want = "a name"
    if not ok:
        raise UsageError(f"{spelled}: {want}, got {value!r}")


def apply_named_options(
    kind: Kind,
    cfg: Any,
    source: str,
    values: Mapping[str, Any],
    names: Mapping[str, str],
    *,
    taken: Collection[str] | None = None,
) -> Any:
    """:func:`apply_options`, its errors naming each option as ``names`` spell it (the
    command line's flags: :data:`OPTIONS`; :mod:`covnet.cli.api` names its arguments).
    ``taken``: the options the caller has (a refusal lists the kind's options among them;
    ``covnet mc`` of a mobile config listed ``--solver``, which mc does not have); None: all."""
    given = {k: v for k, v in values.items() if v is not None and v != []}
    for name in given:
        if name not in OPTIONS:
            raise ValueError(f"not a run option: {name!r}")
        _check_type(names[name], name, given[name])
        if name not in kind.options:
            offered = [o for o in OPTIONS if taken is None or o in taken]
            takes = ", ".join(names[o] for o in offered if o in kind.options) or "none"
            raise UsageError(
                f"{names[name]}: a {kind.title} scenario does not take this option "
                f"(its options: {takes})"
            )
    if not given:
        return cfg
    data = kind.normalised(cfg)
    for name, value in given.items():
        try:
            kind.options[name](data, value)
        except ValueError as exc:
            raise UsageError(f"{names[name]}: {exc}") from None
    return kind.from_dict(data, f"{source} (with {', '.join(names[n] for n in given)})", None)


def command(kind: Kind, name: str, what: str) -> Callable[..., int]:
    """The kind's implementation of the optional command ``name``; a kind without it is a
    :class:`~covnet.errors.UsageError` that says which kinds have it (``what``: what the
    command does, for the message)."""
    fn = kind.commands.get(name)
    if fn is None:
        have = [k for k in REGISTRY if name in get(k).commands]
        raise UsageError(
            f"{name.split(':')[-1]}: {what} is not defined for a {kind.title} scenario "
            f"(scenario kinds that have it: {', '.join(have) or 'none'})"
        )
    return fn
