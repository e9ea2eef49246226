"""``python -m sensors --config C --id S3 --run RUN --connect tcp/HOST:PORT``: one sensor
(``--id S3 --id S4 ...``: several, each in its own thread with its own session, token and
heartbeat, :mod:`sensors.host`).

The scenario's kind (:mod:`covnet.kinds`) names the module of its sensor
(``sensors.covariance``, ``sensors.mobile``, ``sensors.passive``): ``main(args, cfg, stop)``
serves the commands (:mod:`sensors.protocol`) with that kind's measurement.
"""

from __future__ import annotations

import importlib
import sys

from covnet.processes.process import (
    EXIT_USAGE,
    common_parser,
    guarded,
    load_config,
    resolve_run,
    stop_on_signals,
)


def main(argv: list[str] | None = None) -> int:
    p = common_parser("sensors", "One sensor process: obeys commands, publishes measurements.")
    p.add_argument(
        "--id",
        required=True,
        action="append",
        help="sensor id from the config's sensors table (repeatable: this process hosts every "
        "sensor named, each with its own zenoh session, liveliness token and heartbeat)",
    )
    p.add_argument("--connect", help="router endpoint (default: the config's network)")
    args = p.parse_args(argv)

    def body() -> int:
        stop = stop_on_signals()
        kind, cfg = load_config(args)
        resolve_run(args, cfg)
        ids = list(args.id)
        for sid in ids:
            if sid not in cfg.sensor_ids:
                print(
                    f"sensors: error: --id {sid!r} is not in the config's sensors "
                    f"{list(cfg.sensor_ids)}",
                    file=sys.stderr,
                )
                return EXIT_USAGE
        if len(set(ids)) != len(ids):
            print(f"sensors: error: --id: a sensor named twice in {ids}", file=sys.stderr)
            return EXIT_USAGE
        role = importlib.import_module(kind.roles["sensor"])
        if len(ids) == 1:
            args.id = ids[0]
            return int(role.main(args, cfg, stop))
        from sensors.host import host  # several sensors (start-up of a process of one)

        return host(ids, role.main, args, cfg, stop)

    return guarded(body, "sensors")


if __name__ == "__main__":
    sys.exit(main())
