"""``python -m recorder --config C --run RUN --connect tcp/HOST:PORT --out FILE.mcap
[--foxglove HOST:PORT]``.

The recorder: writes every message of the run to an MCAP file (layout:
:mod:`covnet.runs.recording`).  Exits 0 when the run is over or on SIGINT/SIGTERM, after writing
the file's summary and footer.  It is the same for every scenario kind; the visual channels
(:mod:`covnet.runs.visual`) come from the kind's visual module (``Kind.visual``), and with
``--foxglove`` they are also served live (:mod:`covnet.runs.live`).  Restarted (``network.
restart: on-failure``), it continues in the next segment, ``FILE.2.mcap``, ... (the replay reads
them in order).
"""

from __future__ import annotations

import signal
import sys
from pathlib import Path

from covnet.clock import WallClock
from covnet.processes.process import (
    EXIT_OK,
    common_parser,
    guarded,
    load_config,
    open_client,
    resolve_run,
    stop_on_signals,
)
from covnet.runs.live import LiveView, parse_address
from covnet.runs.recording import RecordingWriter, next_segment, run_metadata
from covnet.runs.visual import Visualiser
from recorder import node


def main(argv: list[str] | None = None) -> int:
    p = common_parser("recorder", "The recorder process: every message of the run to MCAP.")
    p.add_argument("--connect", help="router endpoint (default: the config's network)")
    p.add_argument("--out", required=True, help="MCAP file to write (e.g. RUN_DIR/recording.mcap)")
    p.add_argument(
        "--foxglove",
        metavar="HOST:PORT",
        help="also serve the visual channels live over the Foxglove WebSocket protocol",
    )
    args = p.parse_args(argv)

    def body() -> int:
        stop = stop_on_signals()
        kind, cfg = load_config(args)
        resolve_run(args, cfg)
        out = next_segment(Path(args.out))  # a restarted recorder never overwrites
        out.parent.mkdir(parents=True, exist_ok=True)
        visualiser = Visualiser(kind.visual(cfg), kind.episodes(cfg))
        live = live_visualiser = None
        if args.foxglove:
            host, port = parse_address(args.foxglove)
            live = LiveView(host, port, name=f"covnet {cfg.name} ({args.run})")
            live_visualiser = Visualiser(kind.visual(cfg), kind.episodes(cfg))
            print(f"foxglove: live view on ws://{host}:{live.port}")
        try:
            with open_client(args, cfg.network, node.ROLE, node.NODE_ID, stop) as bus:
                meta = run_metadata(args.run, cfg)
                with RecordingWriter(
                    out, run_id=args.run, metadata=meta, sensors=cfg.sensor_ids
                ) as w:
                    counts = node.run(
                        cfg, bus, args.run, WallClock(args.speed), stop, w,
                        visualiser=visualiser, live=live, live_visualiser=live_visualiser,
                    )  # fmt: skip
        finally:
            if live is not None:
                live.close()
        print(f"stopped: {w.messages} messages recorded to {out}; {dict(counts)}")
        return EXIT_OK

    rc = guarded(body, "recorder")
    # The recording is closed: a SIGINT from the launcher's stop now must not kill the
    # interpreter while it finalises (the Foxglove SDK's runtime takes a moment to wind down,
    # and a signal then would end the process with -2 instead of its status).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    return rc


if __name__ == "__main__":
    sys.exit(main())
