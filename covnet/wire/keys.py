"""The wire's names: ids (run, role, node, sensor, target) and every key expression covnet
publishes or subscribes to.  Nothing else in covnet formats a key expression; the payloads are
:mod:`covnet.wire.schemas` and :mod:`covnet.wire.codec`'s (all three re-exported by
:mod:`covnet.wire.messages`)."""

from __future__ import annotations

import re
from collections.abc import Iterable

MAX_NAME_LEN = 64
"""Longest id (run, role, node, sensor, target) and ``modes`` value."""

_BAD_NAME = re.compile(r"[/*$?#\s]")


def _name_problem(value: object) -> str | None:
    """Why ``value`` cannot be an id / key chunk, or None when it can."""
    if not isinstance(value, str):
        return f"must be a str, got {type(value).__name__}"
    if not value:
        return "must be non-empty"
    if len(value) > MAX_NAME_LEN:
        return f"longer than {MAX_NAME_LEN} characters"
    if _BAD_NAME.search(value) or not value.isprintable():
        return "must not contain '/', '*', '$', '?', '#', whitespace or control characters"
    return None


# Ids already found valid: most keys and messages repeat the same few, and checking one costs
# a regex search.  Bounded: once full, new ids are checked every time.
_GOOD_NAMES: set[str] = set()
_GOOD_NAMES_MAX = 4096


def _valid(value: object, what: str) -> str:
    if type(value) is str and value in _GOOD_NAMES:
        return value
    problem = _name_problem(value)
    if problem is not None:
        raise ValueError(f"invalid {what} {value!r}: {problem}")
    assert isinstance(value, str)
    if type(value) is str and len(_GOOD_NAMES) < _GOOD_NAMES_MAX:
        _GOOD_NAMES.add(value)
    return value


MANAGER_ID, WORLD_ID, RECORDER_ID = "manager", "world", "recorder"
"""Node ids of the processes that are not sensors (each is also its role's name)."""
RESERVED_IDS = (MANAGER_ID, WORLD_ID, RECORDER_ID)
"""A sensor may not use one of these ids when security is on (they are zenoh identities)."""


def new_run_id() -> str:
    """A short unique run id (12 hex digits), valid as a key chunk."""
    import uuid  # start-up: only where a run id is made

    return uuid.uuid4().hex[:12]


#: a run of at most this many scans gets the truth of every scan at once (the world then hears
#: no command, and sensors keep it for the whole run); a longer one gets it window by window,
#: paced by the commands (:mod:`world.covariance`)
TRUTH_UPFRONT_MAX_SCANS = 5000


def _root(run: str) -> str:
    return f"covnet/{_valid(run, 'run id')}"


def run_keyexpr(run: str) -> str:
    """``covnet/<run>/**``: every publication of one run (what the recorder subscribes to)."""
    return f"{_root(run)}/**"


def truth_key(run: str) -> str:
    """``covnet/<run>/truth``: ground truth, one :class:`Truth` per scan (world -> sensors)."""
    return f"{_root(run)}/truth"


_CMD_SEP = "~"  # never in an id (see _BAD_NAME's ids: config ids are [A-Za-z0-9_.-])


def command_key(run: str, enabled: Iterable[str]) -> str:
    """``covnet/<run>/cmd/~S1~S3~``: the key of the :class:`Command` that enables
    ``enabled`` (in the command's order; ``covnet/<run>/cmd/~`` when it enables none).  One
    put per scan, and zenoh routes it by its key: to the sensors it enables
    (:func:`command_keyexpr` ``(run, id)``) and to whoever hears every command, never to a
    disabled sensor, which is then not even woken (manager -> sensors, recorder)."""
    ids = [_valid(sid, "sensor id") for sid in enabled]
    if any(_CMD_SEP in sid for sid in ids):
        raise ValueError(f"invalid sensor id in {ids!r}: must not contain {_CMD_SEP!r}")
    return f"{_root(run)}/cmd/{_enabled_chunk(ids)}"


def _enabled_chunk(ids: Iterable[str]) -> str:
    """The last chunk of a command key: ``~S1~S3~`` (``~`` for none)."""
    return _CMD_SEP + "".join(sid + _CMD_SEP for sid in ids)


def command_keyexpr(run: str, sensor_id: str | None = None) -> str:
    """Commands: those that enable ``sensor_id`` (``covnet/<run>/cmd/$*~<id>~$*``, zenoh's
    sub-chunk wildcard), or every one (``covnet/<run>/cmd/*``: the recorder, a world that
    paces the truth by the commands, a sensor on slow links, which must see every command to
    notice one it missed)."""
    if sensor_id is None:
        return f"{_root(run)}/cmd/*"
    return f"{_root(run)}/cmd/$*{_CMD_SEP}{_valid(sensor_id, 'sensor id')}{_CMD_SEP}$*"


def parse_command_key(key: str) -> tuple[str, ...]:
    """The enabled ids a concrete command key names; ValueError for any other key."""
    parts = key.split("/")
    if len(parts) != 4 or parts[0] != "covnet" or parts[2] != "cmd":
        raise ValueError(f"not a command key: {key!r}")
    _valid(parts[1], "run id")
    chunk = parts[3]
    if len(chunk) < 1 or chunk[0] != _CMD_SEP or chunk[-1] != _CMD_SEP:
        raise ValueError(f"not a command key: {key!r}")
    if chunk == _CMD_SEP:
        return ()
    return tuple(_valid(sid, "sensor id") for sid in chunk[1:-1].split(_CMD_SEP))


def measurement_key(run: str, sensor_id: str) -> str:
    """``covnet/<run>/sensor/<id>/meas``: one sensor's :class:`Measurement` s."""
    return f"{_root(run)}/sensor/{_valid(sensor_id, 'sensor id')}/meas"


def measurement_keyexpr(run: str) -> str:
    """``covnet/<run>/sensor/*/meas``: every sensor's measurements."""
    return f"{_root(run)}/sensor/*/meas"


def parse_measurement_key(key: str) -> str:
    """The sensor id of a concrete measurement key (to check it against the payload's)."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != "covnet" or parts[2] != "sensor" or parts[4] != "meas":
        raise ValueError(f"not a measurement key: {key!r}")
    _valid(parts[1], "run id")
    return _valid(parts[3], "sensor id")


def peer_track_key(run: str, node_id: str) -> str:
    """``covnet/<run>/peer/<id>/track``: a peer node's own fused :class:`Track` (peer mode)."""
    return f"{_root(run)}/peer/{_valid(node_id, 'node id')}/track"


def peer_status_key(run: str, node_id: str) -> str:
    """``covnet/<run>/peer/<id>/status``: a peer node's :class:`Status` per scan (peer mode):
    the enabled set it decided, the tracks it fused, the members it excluded."""
    return f"{_root(run)}/peer/{_valid(node_id, 'node id')}/status"


def peer_keyexpr(run: str, what: str = "*") -> str:
    """``covnet/<run>/peer/*/<what>``: every peer node's tracks or statuses (or both: ``*``)."""
    return f"{_root(run)}/peer/*/{what}"


def parse_peer_key(key: str) -> tuple[str, str]:
    """``(node_id, "track" | "status")`` of a concrete peer key; ValueError for anything else."""
    parts = key.split("/")
    if (
        len(parts) != 5
        or parts[0] != "covnet"
        or parts[2] != "peer"
        or parts[4] not in ("track", "status")
    ):
        raise ValueError(f"not a peer key: {key!r}")
    _valid(parts[1], "run id")
    return _valid(parts[3], "node id"), parts[4]


def track_key(run: str) -> str:
    """``covnet/<run>/track``: the fused :class:`Track` per scan (manager)."""
    return f"{_root(run)}/track"


def status_key(run: str) -> str:
    """``covnet/<run>/manager/status``: the manager's :class:`Status` per scan."""
    return f"{_root(run)}/manager/status"


def heartbeat_key(run: str, role: str, node_id: str) -> str:
    """``covnet/<run>/hb/<role>/<id>``: a node's :class:`Heartbeat` (last scan it handled)."""
    return f"{_root(run)}/hb/{_valid(role, 'role')}/{_valid(node_id, 'node id')}"


def heartbeat_keyexpr(run: str) -> str:
    """``covnet/<run>/hb/*/*``: every node's heartbeats."""
    return f"{_root(run)}/hb/*/*"


def alive_key(run: str, role: str, node_id: str) -> str:
    """``covnet/<run>/alive/<role>/<id>``: a node's liveliness token."""
    return f"{_root(run)}/alive/{_valid(role, 'role')}/{_valid(node_id, 'node id')}"


DONE_ID = "done"
"""The id of the manager's second token, :func:`done_key`."""


def done_key(run: str) -> str:
    """``covnet/<run>/alive/manager/done``: the token a manager declares as it ends the run on
    purpose (finished, or stopped), just before its own token goes: the nodes then leave at
    once, while a manager token lost without it (a crash, a link down for a while) is waited
    for (:class:`covnet.processes.node_kit.ManagerWatch`)."""
    return alive_key(run, "manager", DONE_ID)


FAILED_ID = "failed"
"""The id of the token a manager declares instead of :data:`DONE_ID` when its run ended with an
error, :func:`failed_key`."""


def failed_key(run: str) -> str:
    """``covnet/<run>/alive/manager/failed``: as :func:`done_key` (the nodes leave at once),
    for a run that ended with an error (nodes of another config, nodes never up, a forged
    end): a node that leaves on it says so and exits 1, where it exits 0 after
    :func:`done_key`."""
    return alive_key(run, "manager", FAILED_ID)


def alive_keyexpr(run: str, role: str | None = None) -> str:
    """``covnet/<run>/alive/<role>/*`` (or ``alive/*/*`` for every role): liveliness tokens."""
    return f"{_root(run)}/alive/{'*' if role is None else _valid(role, 'role')}/*"


def parse_alive_key(key: str) -> tuple[str, str]:
    """``(role, node_id)`` of a concrete liveliness key; ValueError for anything else."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != "covnet" or parts[2] != "alive":
        raise ValueError(f"not a liveliness key: {key!r}")
    _valid(parts[1], "run id")
    return _valid(parts[3], "role"), _valid(parts[4], "node id")
