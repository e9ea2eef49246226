"""``python -m manager --config C --run RUN --listen tcp/127.0.0.1:PORT --out DIR``.

The fusion manager; its zenoh session is the network's router (world and sensors connect to
it).  Prints ``READY`` once every expected node is alive, one ``STATUS {json}`` line per scan
(at most ~20 per second, and always the last one), and writes the run directory as it goes:
after each episode, about once a second, and when stopped.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from covnet.clock import WallClock
from covnet.process import (
    EXIT_FAIL,
    EXIT_OK,
    common_parser,
    guarded,
    load_config,
    open_bus,
    resolve_run,
    stop_on_signals,
)


def main(argv: list[str] | None = None) -> int:
    p = common_parser("manager", "The fusion manager: allocates, commands, fuses.")
    p.add_argument("--listen", help="router endpoint to listen on (default: network.router)")
    p.add_argument("--out", required=True, help="run directory to write")
    p.add_argument("--metric", action="append", help="metric(s) to run (default: the config's)")
    p.add_argument("--solver", help="kind: mobile only: the decision's solver (default: config's)")
    args = p.parse_args(argv)

    def body() -> int:
        from covnet.process import is_mobile
        from manager import node
        from manager.report import write_network_run

        stop = stop_on_signals()
        sc = load_config(args.config, args.seed)
        resolve_run(args, sc)
        if is_mobile(sc):
            from covnet.mobile.nodes.manager import main_body

            return main_body(args, sc, stop)
        if args.solver is not None:
            raise ValueError("--solver: only a mobile scenario (kind: mobile) has solvers")
        metrics = args.metric or list(sc.allocation.metrics)
        from covnet.core.metrics import METRICS

        for m in metrics:
            if m not in METRICS:
                raise ValueError(f"--metric: unknown metric {m!r}; choose from {sorted(METRICS)}")
        from covnet import security

        endpoint = security.endpoint(sc.network, args.listen or sc.network.router)
        if endpoint.endswith(":0"):
            raise ValueError(f"--listen: give a concrete port, got {endpoint!r}")
        out = Path(args.out)
        run_info = {
            "episodes": metrics,
            "run_id": args.run,
            "clock": "realtime" if args.realtime else "lockstep",
            "speed": args.speed,
            "router": endpoint,
        }
        last_write = [time.monotonic()]
        last_status = [0.0]

        def on_ready() -> None:
            print("READY", flush=True)

        def on_status(st: dict[str, object]) -> None:
            now = time.monotonic()
            if now - last_status[0] >= 0.05 or st["scan"] == st["scans"]:
                print("STATUS " + json.dumps(st), flush=True)
                last_status[0] = now

        def on_progress(result: node.ManagerResult, episode_done: bool) -> None:
            now = time.monotonic()
            if episode_done or now - last_write[0] >= 1.0:
                write_network_run(out, sc, result, run_info)
                last_write[0] = time.monotonic()

        extra = security.zenoh_settings(
            sc.network,
            "manager",
            "manager",
            listen=True,
            sensor_ids=sc.sensor_ids,
            source=args.config,
        )
        with open_bus(
            "router",
            listen=[endpoint],
            lease_ms=sc.network.lease_ms,
            timeout_s=sc.network.ready_timeout_s,
            stop=stop,
            extra_json5=extra,
        ) as bus:
            print(f"LISTENING {endpoint}", flush=True)
            result = node.run(
                sc,
                metrics,
                bus,
                args.run,
                WallClock(args.speed),
                stop,
                realtime=args.realtime,
                on_ready=on_ready,
                on_status=on_status,
                on_progress=on_progress,
            )
            # the run is over (our token is gone): the nodes leave on their own; keep the
            # router up until they have, so that none is cut off mid-publish
            node.wait_for_nodes_to_leave(bus, args.run, timeout_s=5.0, stop=stop)
        write_network_run(out, sc, result, run_info)
        if result.error:
            print(f"manager: error: {result.error}", file=sys.stderr, flush=True)
            return EXIT_FAIL
        print(f"DONE completed={result.completed} out={out}", flush=True)
        return EXIT_OK

    return guarded(body, "manager")


if __name__ == "__main__":
    sys.exit(main())
