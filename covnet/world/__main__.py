"""``python -m covnet.world --config C --run RUN --connect tcp/HOST:PORT``: the world."""

from __future__ import annotations

import sys

from covnet.clock import WallClock
from covnet.process import (
    EXIT_OK,
    common_parser,
    guarded,
    load_config,
    open_client,
    resolve_run,
    stop_on_signals,
)


def main(argv: list[str] | None = None) -> int:
    p = common_parser("world", "The world process: publishes ground truth each scan.")
    p.add_argument("--connect", help="router endpoint (default: the config's network)")
    args = p.parse_args(argv)

    def body() -> int:
        from covnet.process import is_mobile, is_passive
        from covnet.world import node

        stop = stop_on_signals()
        sc = load_config(args.config, args.seed, args.fusion)
        if is_mobile(sc):  # kind: mobile -> the mobile world (targets and platforms)
            from covnet.mobile.nodes import world as node  # type: ignore[no-redef]
        elif is_passive(sc):  # kind: passive -> the target positions
            from covnet.passive.nodes import world as node  # type: ignore[no-redef]
        resolve_run(args, sc)
        with open_client(args, sc.network, "world", "world", stop) as bus:
            counts = node.run(sc, bus, args.run, WallClock(args.speed), stop)
        print(f"stopped: {dict(counts)}")
        return EXIT_OK

    return guarded(body, "world")


if __name__ == "__main__":
    sys.exit(main())
