"""What every node process (world, sensor, manager) does around its loop.

``python -m sensors --config C --id S3 --run RUN --connect tcp/HOST:PORT`` (likewise
``python -m manager``, ``python -m world`` and ``python -m recorder``): load and validate the
config (its kind from the registry), open the zenoh session (retrying while the router is not up
yet, up to ``network.ready_timeout_s``), turn SIGINT/SIGTERM into a stop event the loop polls,
run the loop, close the session, exit.

Exit status: 0 stopped or finished cleanly, 1 the loop failed, 2 a user's mistake (bad config
or option; one readable line on stderr, no traceback).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from covnet import kinds
from covnet.config import (
    ConfigError,
    NetworkSpec,
    endpoint_problem,
    endpoint_security_problem,
    hash_of,
)
from covnet.errors import NoRun, UsageError
from covnet.processes.launch import EXIT_NO_RUN as EXIT_NO_RUN  # the nodes' too
from covnet.processes.launch import EXIT_RUN_FAILED as EXIT_RUN_FAILED
from covnet.runs.rundir import os_error_text
from covnet.wire import security
from covnet.wire.keys import run_keyexpr

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


def common_parser(prog: str, description: str) -> argparse.ArgumentParser:
    """The options every node process takes: the config, the run id, the run options (each a
    change of the config, given to every process of a network alike), the clock."""
    p = argparse.ArgumentParser(prog=prog, description=description)
    p.add_argument("--config", required=True, help="scenario YAML (the single source of truth)")
    p.add_argument(
        "--run",
        help="run id: the key prefix shared by one network (default: derived from the config, "
        "'<name>-<hash>', the same for every process started with the same config)",
    )
    p.add_argument("--seed", type=int, help="override the config's seed")
    p.add_argument("--metric", action="append", help="the metric(s) to run (covariance control)")
    p.add_argument("--fusion", help="override the config's fusion.mode (covariance control)")
    p.add_argument("--solver", help="override the config's solver (kind: mobile)")
    p.add_argument("--realtime", action="store_true", help="pace scans by the config's period")
    p.add_argument("--speed", type=float, default=1.0, help="real-time speed factor")
    p.add_argument(
        "--no-app-latency",
        action="store_true",
        help="do not emulate network.latency inside the process (a real emulated path, "
        "covnet up --netns, delays the packets instead)",
    )
    return p


RUN_OPTIONS = ("seed", "metric", "fusion", "solver")
"""The node options that change the config (:data:`covnet.kinds.OPTIONS`)."""


def run_option_args(options: dict[str, Any]) -> list[str]:
    """The command-line arguments that give a node process the run ``options`` (``None``
    values are not given): how ``covnet up`` passes them on, to every process alike."""
    argv: list[str] = []
    for name in RUN_OPTIONS:
        value = options.get(name)
        if value is None:
            continue
        for v in value if isinstance(value, list) else [value]:
            argv += [f"--{name}", str(v)]
    return argv


def load_config(args: Any) -> tuple[Any, Any]:
    """``(kind, config)`` of ``args.config`` with the run options of ``args`` applied (the
    kind registry decides the kind, from one parse of the file)."""
    kind, cfg = kinds.load(args.config)
    values = {n: getattr(args, n, None) for n in RUN_OPTIONS}
    return kind, kinds.apply_options(kind, cfg, args.config, **values)


def default_run_id(cfg: Any) -> str:
    """The run id processes started separately agree on without being told: ``name-hash``,
    the hash of what every host of the run holds alike (:func:`covnet.processes.node_kit.
    shared_config`: the config without ``network.router``, ``network.connect``,
    ``network.security`` and ``allocation.metrics``), the config identity's own data.  A
    separate hash that dropped ``network.security`` only gave the manager's host, the one
    given ``--metric``, or a host whose copy names ``connect`` where the other's names
    ``router``, another run id: the hosts never met, and every one exited 1 after
    ``ready_timeout_s`` (hunt 14).  The run's clock (``--realtime``, ``--speed``) is left out
    too: hosts that differ there meet, and the identity check refuses them by name."""
    from covnet.processes.node_kit import shared_config  # (a node's start-up, not the CLI's)

    return f"{cfg.name}-{hash_of(shared_config(cfg))[:8]}"


def resolve_run(args: Any, cfg: Any) -> str:
    """``--run`` or the default; sets ``args.run`` so the rest of a ``main`` can use it.  The
    node's options that name the wire are checked here, before a session opens, as ``covnet
    up`` checks them: ``--run`` (a key chunk) and ``--connect`` / ``--listen`` (endpoints; a
    malformed one was retried until ``ready_timeout_s``)."""
    if args.run is not None:
        try:
            run_keyexpr(args.run)  # validates like every key part, as covnet up does
        except ValueError as exc:
            raise UsageError(f"--run: {exc}") from None
    for option in ("connect", "listen"):
        value = getattr(args, option, None)
        if value is not None and (
            (problem := endpoint_problem(value)) is not None
            or (problem := endpoint_security_problem(value, cfg.network)) is not None
        ):
            raise UsageError(f"--{option}: {problem}")
    args.run = args.run or default_run_id(cfg)
    # the clock options are part of the identity every node's heartbeats carry
    from covnet.processes.node_kit import set_run_clock  # (a node's start-up, not the CLI's)

    set_run_clock(bool(getattr(args, "realtime", False)), float(getattr(args, "speed", 1.0)))
    return str(args.run)


def stop_on_signals() -> threading.Event:
    """SIGINT, SIGTERM and SIGHUP set the returned event (the loop then winds down and
    returns)."""
    stop = threading.Event()

    def handler(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGHUP, handler)
    return stop


REFUSED_FOR_S = 2.0
"""A client gives up before ``ready_timeout_s`` once the router has been there and refused its
session (:func:`covnet.wire.security.login_problem`) for this long."""

ROUTER_RETRY_S = 2.0
"""A router whose listener cannot be opened (the port taken, the address not on this host)
gives up after this long, not at ``ready_timeout_s``: waiting does not free an address, and
this is long enough for a router of a run just ended to let its port go."""


def open_bus(
    mode: str,
    *,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    lease_ms: int | None,
    timeout_s: float,
    stop: threading.Event,
    extra_json5: dict[str, object] | None = None,
    express: bool = False,
    diagnose: Callable[[], str | None] | None = None,
) -> Any:
    """Open a :class:`~covnet.wire.zenoh_bus.ZenohBus`, retrying a client's connection for up to
    ``timeout_s`` (so processes may start in any order, as on several hosts), a router's listener
    for up to :data:`ROUTER_RETRY_S`.

    ``diagnose``: asked, at most every 0.5 s, after a failed attempt, why the session does not
    open; a text means the router is there and refuses it (a wrong password, a certificate it
    does not accept). After :data:`REFUSED_FOR_S` of refusals, or at ``timeout_s``, the
    ``ConnectionError`` starts with that text, zenoh's own message in parentheses after it."""
    # imported here: zenoh is for the node processes, not for the launcher and the CLI that
    # use this module too (start-up time)
    from covnet.wire.zenoh_bus import ZenohBus, zenoh_config

    wait_s = min(timeout_s, ROUTER_RETRY_S) if mode == "router" else timeout_s
    deadline = time.monotonic() + wait_s
    verdict: str | None = None
    refused_since: float | None = None
    next_look = 0.0
    while True:
        try:
            config = zenoh_config(
                mode,  # type: ignore[arg-type]  # "router" or "client", checked by zenoh_config
                listen=list(listen),
                connect=list(connect),
                lease_ms=lease_ms,
                extra_json5=extra_json5,
            )
            return ZenohBus.open(config, express=express)
        except Exception as exc:  # zenoh raises its own ZError
            now = time.monotonic()
            give_up = now > deadline or stop.is_set()
            if diagnose is not None and not stop.is_set() and (give_up or now >= next_look):
                verdict = diagnose()
                next_look = time.monotonic() + 0.5
                if verdict is None:
                    refused_since = None
                elif refused_since is None:
                    refused_since = now
            if refused_since is not None and now - refused_since >= REFUSED_FOR_S:
                give_up = True
            if give_up:
                where = f"cannot open a zenoh {mode} session ({listen or connect})"
                # a client that cannot join has no run to join (not restarted); a router's
                # listener that cannot open is the manager's failure
                error = NoRun if mode == "client" else ConnectionError
                if verdict is not None:
                    raise error(f"{verdict}: {where} (zenoh: {exc})") from None
                raise error(f"{where}: {exc}") from None
            stop.wait(0.1)


def open_client(args: Any, net: NetworkSpec, role: str, node_id: str, stop: threading.Event) -> Any:
    """The client session of a world, sensor or recorder process: the endpoint from
    ``--connect`` or the config (``tls/`` when TLS is on), this node's security settings,
    retries while the router is not up yet. With passwords or TLS, a router that refuses this
    node is named as such: ``authentication failed for <node> (...)`` or ``TLS handshake failed
    for <node> (...)`` (:func:`covnet.wire.security.login_problem`), within about
    :data:`REFUSED_FOR_S` rather than at ``ready_timeout_s``.

    ``args.shared_bus`` (set by a process hosting several sensors of the same session
    settings, :mod:`sensors.host`): a :meth:`~covnet.wire.zenoh_bus.ZenohBus.share` of it instead
    of a session of its own."""
    shared = getattr(args, "shared_bus", None)
    if shared is not None:  # a hosted sensor on its host's one session (sensors.host)
        return shared.share()
    endpoint = security.endpoint(net, args.connect or net.connect or net.router)
    extra = security.zenoh_settings(net, role, node_id, listen=False, source=args.config)

    def diagnose() -> str | None:
        return security.login_problem(net, node_id, endpoint)

    return open_bus(
        "client",
        connect=[endpoint],
        lease_ms=net.lease_ms,
        timeout_s=net.ready_timeout_s,
        stop=stop,
        extra_json5=extra,
        diagnose=diagnose if net.security.authenticated else None,
    )


def guarded(body: Callable[[], int], prog: str) -> int:
    """Run ``body``; a user's mistake prints one line and exits 2, a failure exits 1 (a file
    that could not be written, a full disk: one line naming it, no traceback), a node that
    found no run to join (:class:`~covnet.errors.NoRun`) :data:`EXIT_NO_RUN`."""
    try:
        return body()
    except ConfigError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except UsageError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except NoRun as exc:  # no run to join: not restarted (before ConnectionError, its base)
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_NO_RUN
    except (ValueError, ConnectionError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_FAIL
    except OSError as exc:  # the node's files (the run directory, the recording)
        print(f"{prog}: error: {os_error_text(exc)}", file=sys.stderr)
        return EXIT_FAIL
