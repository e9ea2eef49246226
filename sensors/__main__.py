"""``python -m sensors --config C --id S3 --run RUN --connect tcp/HOST:PORT``: one sensor.

The scenario's kind (:mod:`covnet.kinds`) names the module of its sensor
(``sensors.covariance``, ``sensors.mobile``, ``sensors.passive``): ``main(args, cfg, stop)``
serves the commands (:mod:`sensors.protocol`) with that kind's measurement.
"""

from __future__ import annotations

import importlib
import sys

from covnet.process import (
    EXIT_USAGE,
    common_parser,
    guarded,
    load_config,
    resolve_run,
    stop_on_signals,
)


def main(argv: list[str] | None = None) -> int:
    p = common_parser("sensors", "One sensor process: obeys commands, publishes measurements.")
    p.add_argument("--id", required=True, help="sensor id from the config's sensors table")
    p.add_argument("--connect", help="router endpoint (default: the config's network)")
    args = p.parse_args(argv)

    def body() -> int:
        stop = stop_on_signals()
        kind, cfg = load_config(args)
        resolve_run(args, cfg)
        if args.id not in cfg.sensor_ids:
            print(
                f"sensors: error: --id {args.id!r} is not in the config's sensors "
                f"{list(cfg.sensor_ids)}",
                file=sys.stderr,
            )
            return EXIT_USAGE
        role = importlib.import_module(kind.roles["sensor"])
        return int(role.main(args, cfg, stop))

    return guarded(body, "sensors")


if __name__ == "__main__":
    sys.exit(main())
