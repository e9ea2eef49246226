"""Several sensors in one process (``python -m sensors --id S1 --id S2 ...``,
``covnet up --sensors-per-process K``).

One process per sensor does not scale on a few cores (each is an interpreter, a zenoh session and
its threads, woken every scan), so a process may host several sensors.  Each hosted sensor is
exactly what it would be alone: its own thread runs the kind's sensor ``main`` (its own
subscriptions, publishers, liveliness token and heartbeat, :func:`sensors.protocol.serve`), so
the manager sees the same protocol and the same keys as from one process per sensor.

Sessions: when every hosted sensor's zenoh settings are the same (security off, or a shared
identity), the process opens **one** client session and each sensor works on a
:meth:`~covnet.wire.zenoh_bus.ZenohBus.share` of it (its own entities, undeclared when it stops).
64 sensors per process then cost the router one transport, not 64 handshakes, leases and
transmission pipelines, which is what kept a 256-sensor network from becoming ready in time on
two cores.  Sensors with identities of their own (per-node passwords or certificates) each
open their own session, as alone.  They share the interpreter, the signal handling (SIGINT or
SIGTERM stops them all) and the fate of the process: killing it takes out all its sensors, which
the manager then sees fail one by one, as it would separate processes.

A hosted sensor that fails (its session cannot open, its loop raises) stops the others and the
process exits with the worst status (1 a failure, 2 a user's mistake), so that a supervisor sees
the host fail and can restart it whole.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import traceback
from collections.abc import Callable
from typing import Any

from covnet.config import ConfigError
from covnet.errors import NoRun, UsageError
from covnet.processes.process import (
    EXIT_FAIL,
    EXIT_NO_RUN,
    EXIT_OK,
    EXIT_RUN_FAILED,
    EXIT_USAGE,
    open_client,
)
from covnet.wire import security

__all__ = ["host", "say"]

SensorMain = Callable[[Any, Any, threading.Event], int]

#: the main thread's longest wait (signal handlers run in the main thread, between waits)
_SLICE_S = 0.1
# the statuses of sensors that left for no failure of their own, the first ranking higher:
# no run to join, or a run that did not end well
_NOT_THEIR_OWN = (EXIT_NO_RUN, EXIT_RUN_FAILED)


_say_lock = threading.Lock()


def say(args: Any, text: str) -> None:
    """One line of a sensor on stdout, whole (the hosted sensors' threads share it), prefixed
    with the sensor's id when it is hosted (``"S3: stopped: ..."``)."""
    prefix = f"{args.id}: " if getattr(args, "hosted", False) else ""
    with _say_lock:
        sys.stdout.write(f"{prefix}{text}\n")
        sys.stdout.flush()


def one_session(ids: list[str], args: Any, cfg: Any) -> bool:
    """Whether the hosted sensors ``ids`` can share one session: the same zenoh settings."""
    net = cfg.network
    settings = [
        security.zenoh_settings(net, "sensor", sid, listen=False, source=args.config) for sid in ids
    ]
    return all(s == settings[0] for s in settings[1:])


def host(
    ids: list[str],
    main: SensorMain,
    args: Any,
    cfg: Any,
    stop: threading.Event,
    *,
    share: bool | None = None,
) -> int:
    """Run ``main(args_j, cfg, stop)`` for every sensor id of ``ids`` in its own thread
    (``args_j``: ``args`` with ``id`` set to it, and ``shared_bus`` the process's one session
    when ``share``, by default :func:`one_session`), until all have returned; returns the worst
    exit status.  ``stop`` (set by the process's signal handlers) stops them all, and so does
    any hosted sensor that fails."""
    if share is None:
        share = one_session(ids, args, cfg)
    if not share:
        return _run_all(ids, main, args, cfg, stop)
    with open_client(args, cfg.network, "sensor", ids[0], stop) as bus:
        # host_ids: the sensors that may share one protocol loop (sensors.protocol.HostLoop)
        shared = argparse.Namespace(**vars(args), shared_bus=bus, host_ids=list(ids))
        return _run_all(ids, main, shared, cfg, stop)


def _run_all(ids: list[str], main: SensorMain, args: Any, cfg: Any, stop: threading.Event) -> int:
    codes: dict[str, int] = {}
    lock = threading.Lock()

    def one(sid: str) -> None:
        a = argparse.Namespace(**vars(args))
        a.id, a.hosted = sid, True
        code = EXIT_FAIL
        try:
            code = int(main(a, cfg, stop))
        except (ConfigError, UsageError) as exc:
            print(f"sensors: {sid}: error: {exc}", file=sys.stderr, flush=True)
            code = EXIT_USAGE
        except NoRun as exc:  # no run to join: not restarted
            print(f"sensors: {sid}: error: {exc}", file=sys.stderr, flush=True)
            code = EXIT_NO_RUN
        except (ValueError, ConnectionError) as exc:
            print(f"sensors: {sid}: error: {exc}", file=sys.stderr, flush=True)
        except Exception:  # noqa: BLE001 (a hosted sensor's crash must not go unsaid)
            print(f"sensors: {sid}: crashed:", file=sys.stderr, flush=True)
            traceback.print_exc()
        finally:
            with lock:
                codes[sid] = code
            if code != EXIT_OK:
                stop.set()  # the host fails as a whole

    # the hosted sensors' threads must not take SIGINT/SIGTERM: the main thread does
    threads = [threading.Thread(target=one, args=(sid,), name=f"sensor-{sid}") for sid in ids]
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        for th in threads:
            th.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
    for th in threads:
        while th.is_alive():
            th.join(_SLICE_S)
    # a sensor's own failure outranks finding no run and leaving with a run that did not end
    # well (the others then stop with it: their status is that failure's, and a restart may
    # follow)
    failed = sorted(s for s, c in codes.items() if c not in (EXIT_OK, *_NOT_THEIR_OWN))
    if failed:
        print(f"sensors: hosted sensors failed: {failed}", file=sys.stderr, flush=True)
        return max(codes[s] for s in failed)
    return next((c for c in _NOT_THEIR_OWN if c in codes.values()), EXIT_OK)
