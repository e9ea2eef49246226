"""``python -m world --config C --run RUN --connect tcp/HOST:PORT``: the world.

The scenario's kind (:mod:`covnet.kinds`) names the module of its world loop
(``world.covariance``, ``world.mobile``, ``world.passive``): ``run(cfg, bus, run_id, clock,
stop) -> Counter`` publishes the ground truth until the run is over.
"""

from __future__ import annotations

import importlib
import sys

from covnet.clock import WallClock
from covnet.processes.node_kit import MANAGER_LOST, not_ended_well
from covnet.processes.process import (
    EXIT_OK,
    EXIT_RUN_FAILED,
    common_parser,
    guarded,
    load_config,
    open_client,
    resolve_run,
    stop_on_signals,
)
from covnet.wire.messages import WORLD_ID


def main(argv: list[str] | None = None) -> int:
    p = common_parser("world", "The world process: publishes ground truth each scan.")
    p.add_argument("--connect", help="router endpoint (default: the config's network)")
    args = p.parse_args(argv)

    def body() -> int:
        stop = stop_on_signals()
        kind, cfg = load_config(args)
        loop = importlib.import_module(kind.roles["world"])
        resolve_run(args, cfg)
        with open_client(args, cfg.network, WORLD_ID, WORLD_ID, stop) as bus:
            counts = loop.run(cfg, bus, args.run, WallClock(args.speed), stop)
        lost = counts.pop(MANAGER_LOST, 0)
        print(f"stopped: {dict(counts)}")
        if lost:  # the sensors' host of a run whose manager's host died: not a completed run
            print(not_ended_well(args.run, "the world"), flush=True)
            return EXIT_RUN_FAILED
        return EXIT_OK

    return guarded(body, "world")


if __name__ == "__main__":
    sys.exit(main())
