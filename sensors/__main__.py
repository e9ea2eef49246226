"""``python -m sensors --config C --id S3 --run RUN --connect tcp/HOST:PORT``: one sensor."""

from __future__ import annotations

import sys

from covnet.clock import WallClock
from covnet.process import (
    EXIT_OK,
    EXIT_USAGE,
    common_parser,
    guarded,
    load_config,
    open_client,
    resolve_run,
    stop_on_signals,
)


def main(argv: list[str] | None = None) -> int:
    p = common_parser("sensors", "One sensor process: obeys commands, publishes measurements.")
    p.add_argument("--id", required=True, help="sensor id from the config's sensors table")
    p.add_argument("--connect", help="router endpoint (default: the config's network)")
    p.add_argument(
        "--metric", action="append", help="peer mode: metric episode(s) (default: the config's)"
    )
    args = p.parse_args(argv)

    def body() -> int:
        from covnet.process import is_mobile, is_passive
        from sensors import node

        stop = stop_on_signals()
        sc = load_config(args.config, args.seed, args.fusion)
        if is_mobile(sc):  # kind: mobile -> measures its commanded targets
            from covnet.mobile.nodes import sensor as node  # type: ignore[no-redef]
        elif is_passive(sc):  # kind: passive -> its list of angle pairs per scan
            from covnet.passive.nodes import sensor as node  # type: ignore[no-redef]
        resolve_run(args, sc)
        if args.id not in sc.sensor_ids:
            print(
                f"sensors: error: --id {args.id!r} is not in the config's sensors "
                f"{list(sc.sensor_ids)}",
                file=sys.stderr,
            )
            return EXIT_USAGE
        if not (is_mobile(sc) or is_passive(sc)) and sc.fusion.mode == "peer":
            return _peer(args, sc, stop)
        with open_client(args, sc.network, "sensor", args.id, stop) as bus:
            delayed = None
            if app_latency(args, sc):  # network.latency emulated in this process
                from covnet.latency_bus import for_sensor

                delayed = for_sensor(bus, sc, args.id, args.run, args.speed)
            try:
                stats = node.run(sc, args.id, delayed or bus, args.run, WallClock(args.speed), stop)
            finally:
                if delayed is not None:
                    delayed.close()
        print(
            f"stopped: {stats.commands} commands received, {stats.enabled_scans} scans enabled, "
            f"{stats.measurements_sent} measurements sent, rejected {dict(stats.rejected)}"
        )
        return EXIT_OK

    return guarded(body, "sensors")


def app_latency(args, sc) -> bool:  # type: ignore[no-untyped-def]
    """Emulate ``network.latency`` inside this process: a covariance-control scenario with
    links that are not ideal, in real time, unless a real emulated path does it
    (``--no-app-latency``, set by ``covnet up --netns``)."""
    from covnet.process import is_mobile, is_passive

    if is_mobile(sc) or is_passive(sc) or not args.realtime or args.no_app_latency:
        return False
    return not sc.network.latency.is_ideal(sc.sensor_ids)


def _peer(args, sc, stop) -> int:  # type: ignore[no-untyped-def]
    """``fusion.mode: peer``: this sensor is a peer node (decides and fuses with its
    neighbours); the episodes are ``--metric`` or the config's metrics."""
    from covnet.core.metrics import METRICS
    from sensors import peer

    if args.realtime:
        raise ValueError("--realtime: peer mode runs in lockstep only")
    metrics = args.metric or list(sc.allocation.metrics)
    for m in metrics:
        if m not in METRICS:
            raise ValueError(f"--metric: unknown metric {m!r}; choose from {sorted(METRICS)}")
    with open_client(args, sc.network, "sensor", args.id, stop) as bus:
        stats = peer.run(sc, args.id, metrics, bus, args.run, WallClock(args.speed), stop)
    print(
        f"stopped: {stats.scans} scans, {stats.tracks_sent} tracks sent, "
        f"{stats.tracks_fused} fused, rejected {dict(stats.rejected)}"
    )
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
