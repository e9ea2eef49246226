"""``python -m manager --config C --run RUN --listen tcp/127.0.0.1:PORT --out DIR``.

The fusion manager; its zenoh session is the network's router (world and sensors connect to
it).  Prints ``READY`` once every expected node is alive, one ``STATUS {json}`` line per scan
(at most ~20 per second, and always the last one), and writes the run directory as it goes:
after each episode, about once a second, and when stopped.

The scenario's kind (:mod:`covnet.kinds`) names the module of its manager
(``manager.covariance``, ``manager.mobile``, ``manager.passive``): ``main(args, cfg, stop)``
runs the scan skeleton (:mod:`manager.loop`) with that kind's maths.
"""

from __future__ import annotations

import importlib
import sys

from covnet.processes.process import (
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
    args = p.parse_args(argv)

    def body() -> int:
        stop = stop_on_signals()
        kind, cfg = load_config(args)
        resolve_run(args, cfg)
        role = importlib.import_module(kind.roles["manager"])
        return int(role.main(args, cfg, stop))

    return guarded(body, "manager")


if __name__ == "__main__":
    sys.exit(main())
