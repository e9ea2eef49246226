"""What every node process (world, sensor, manager) does around its loop.

``python -m sensors --config C --id S3 --run RUN --connect tcp/HOST:PORT`` (likewise
``python -m manager`` and ``python -m covnet.world``): load and validate the config, open the
zenoh session (retrying while the router is not up yet, up to ``network.ready_timeout_s``),
turn SIGINT/SIGTERM into a stop event the loop polls, run the loop, close the session, exit.

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

from covnet.config import (
    FUSION_MODES,
    ConfigError,
    NetworkSpec,
    Scenario,
    config_hash,
    load,
    scenario_kind,
    with_run_overrides,
)

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


def common_parser(prog: str, description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=description)
    p.add_argument("--config", required=True, help="scenario YAML (the single source of truth)")
    p.add_argument(
        "--run",
        help="run id: the key prefix shared by one network (default: derived from the config, "
        "'<name>-<hash>', the same for every process started with the same config)",
    )
    p.add_argument("--seed", type=int, help="override the config's seed")
    p.add_argument("--realtime", action="store_true", help="pace scans by the config's period")
    p.add_argument("--speed", type=float, default=1.0, help="real-time speed factor")
    p.add_argument(
        "--fusion",
        choices=FUSION_MODES,
        help="override the config's fusion.mode (covariance-control scenarios)",
    )
    p.add_argument(
        "--no-app-latency",
        action="store_true",
        help="do not emulate network.latency inside the process (a real emulated path, "
        "covnet up --netns, delays the packets instead)",
    )
    return p


def load_config(path: str, seed: int | None, fusion: str | None = None) -> Any:
    """The scenario of ``path``: a :class:`Scenario`, a mobile config (``kind: mobile``) or a
    passive config (``kind: passive``).  ``fusion`` (a fusion mode) applies to a
    covariance-control scenario only."""
    if fusion is not None and scenario_kind(path) != "covariance_control":
        raise ConfigError(path, [("fusion", "only a covariance-control scenario has fusion modes")])
    if scenario_kind(path) == "passive":
        from covnet.passive import config as passive_config

        pcfg = passive_config.load(path)
        return passive_config.with_overrides(pcfg, path, seed=seed) if seed is not None else pcfg
    if scenario_kind(path) == "mobile":
        from covnet.mobile import config as mobile_config

        cfg = mobile_config.load(path)
        return mobile_config.with_overrides(cfg, path, seed=seed) if seed is not None else cfg
    return with_run_overrides(load(path), seed=seed, fusion=fusion)


def is_mobile(sc: Any) -> bool:
    """Whether ``sc`` is a mobile config.  Its module is looked up, not imported: a config
    object of that class means the module is loaded already, and a covariance-control node
    then does not pay for importing scipy.optimize and scipy.stats at start-up (~0.5 s of
    CPU per process, 11 processes on two cores)."""
    module = sys.modules.get("covnet.mobile.config")
    return module is not None and isinstance(sc, module.MobileConfig)


def is_passive(sc: Any) -> bool:
    """Whether ``sc`` is a passive config (looked up like :func:`is_mobile`)."""
    module = sys.modules.get("covnet.passive.config")
    return module is not None and isinstance(sc, module.PassiveConfig)


def default_run_id(sc: Scenario) -> str:
    """The run id processes started separately agree on without being told: ``name-hash``."""
    if is_mobile(sc):
        from covnet.mobile.config import config_hash as mobile_hash

        return f"{sc.name}-{mobile_hash(sc)[:8]}"  # type: ignore[arg-type]
    if is_passive(sc):
        from covnet.passive.config import config_hash as passive_hash

        return f"{sc.name}-{passive_hash(sc)[:8]}"  # type: ignore[arg-type]
    return f"{sc.name}-{config_hash(sc)[:8]}"


def resolve_run(args: Any, sc: Scenario) -> str:
    """``--run`` or the default; sets ``args.run`` so the rest of a ``main`` can use it."""
    args.run = args.run or default_run_id(sc)
    return str(args.run)


def stop_on_signals() -> threading.Event:
    """SIGINT and SIGTERM set the returned event (the loop then winds down and returns)."""
    stop = threading.Event()

    def handler(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


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
) -> Any:
    """Open a :class:`~covnet.zenoh_bus.ZenohBus`, retrying a client's connection for up to
    ``timeout_s`` (so processes may start in any order, as on several hosts)."""
    from covnet.zenoh_bus import ZenohBus, zenoh_config

    cfg_args = dict(listen=list(listen), connect=list(connect), lease_ms=lease_ms)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return ZenohBus.open(
                zenoh_config(mode, extra_json5=extra_json5, **cfg_args), express=express
            )  # type: ignore[arg-type]
        except Exception as exc:  # zenoh raises its own ZError
            if time.monotonic() > deadline or stop.is_set():
                raise ConnectionError(
                    f"cannot open a zenoh {mode} session ({listen or connect}): {exc}"
                ) from None
            stop.wait(0.1)


def open_client(args: Any, net: NetworkSpec, role: str, node_id: str, stop: threading.Event) -> Any:
    """The client session of a world, sensor or recorder process: the endpoint from
    ``--connect`` or the config (``tls/`` when TLS is on), this node's security settings,
    retries while the router is not up yet."""
    from covnet import security

    endpoint = security.endpoint(net, args.connect or net.connect or net.router)
    extra = security.zenoh_settings(net, role, node_id, listen=False, source=args.config)
    return open_bus(
        "client",
        connect=[endpoint],
        lease_ms=net.lease_ms,
        timeout_s=net.ready_timeout_s,
        stop=stop,
        extra_json5=extra,
    )


def guarded(body: Callable[[], int], prog: str) -> int:
    """Run ``body``; a user's mistake prints one line and exits 2, a failure exits 1."""
    try:
        return body()
    except ConfigError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (ValueError, ConnectionError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_FAIL
