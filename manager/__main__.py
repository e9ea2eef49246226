"""``python -m manager --config C --run RUN --listen tcp/127.0.0.1:PORT --out DIR``.

The fusion manager; its zenoh session is the network's router (world and sensors connect to
it).  Prints ``READY`` once every expected node is alive, one ``STATUS {json}`` line per scan
(at most ~20 per second, and always the last one), and writes the run directory as it goes:
after each episode, about once a second, and when stopped.
"""

from __future__ import annotations

import sys
from pathlib import Path

from covnet.process import (
    common_parser,
    guarded,
    load_config,
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
        from covnet.process import is_mobile, is_passive
        from manager import node
        from manager.report import write_network_run

        stop = stop_on_signals()
        sc = load_config(args.config, args.seed, args.fusion)
        resolve_run(args, sc)
        if is_mobile(sc):
            from covnet.mobile.nodes.manager import main_body

            return main_body(args, sc, stop)
        if is_passive(sc):
            from covnet.passive.nodes.manager import main_body as passive_main

            return passive_main(args, sc, stop)
        if args.solver is not None:
            raise ValueError("--solver: only a mobile scenario (kind: mobile) has solvers")
        metrics = args.metric or list(sc.allocation.metrics)
        from covnet.core.metrics import METRICS

        for m in metrics:
            if m not in METRICS:
                raise ValueError(f"--metric: unknown metric {m!r}; choose from {sorted(METRICS)}")
        from manager.process import router_endpoint, serve
        from manager.process import run_info as base_run_info

        endpoint = router_endpoint(sc.network, args.listen)
        out = Path(args.out)
        run_info = {"episodes": metrics, **base_run_info(args, endpoint)}

        if sc.fusion.mode == "peer":  # no fusion centre: this process only routes and watches
            from manager import peer_monitor

            if args.realtime:
                raise ValueError("--realtime: peer mode runs in lockstep only")

            def run_loop(bus, clock, hooks):  # type: ignore[no-untyped-def]
                return peer_monitor.run(sc, metrics, bus, args.run, clock, stop, **hooks.kwargs())

            def write(result):  # type: ignore[no-untyped-def]
                return peer_monitor.write_peer_run(out, sc, result, run_info)

        else:

            def run_loop(bus, clock, hooks):  # type: ignore[no-untyped-def]
                return node.run(
                    sc,
                    metrics,
                    bus,
                    args.run,
                    clock,
                    stop,
                    realtime=args.realtime,
                    **hooks.kwargs(),
                )

            def write(result):  # type: ignore[no-untyped-def]
                return write_network_run(out, sc, result, run_info)

        return serve(args, sc.network, sc.sensor_ids, stop, endpoint, run_loop, write)

    return guarded(body, "manager")


if __name__ == "__main__":
    sys.exit(main())
