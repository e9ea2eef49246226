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
    args = p.parse_args(argv)

    def body() -> int:
        from covnet.process import is_mobile, is_passive
        from sensors import node

        stop = stop_on_signals()
        sc = load_config(args.config, args.seed)
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
        with open_client(args, sc.network, "sensor", args.id, stop) as bus:
            stats = node.run(sc, args.id, bus, args.run, WallClock(args.speed), stop)
        print(
            f"stopped: {stats.enabled_scans} scans enabled, "
            f"{stats.measurements_sent} measurements sent, rejected {dict(stats.rejected)}"
        )
        return EXIT_OK

    return guarded(body, "sensors")


if __name__ == "__main__":
    sys.exit(main())
