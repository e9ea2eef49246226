"""``python -m recorder --config C --run RUN --connect tcp/HOST:PORT --out FILE.mcap``.

The recorder: writes every message of the run to an MCAP file (layout:
:mod:`covnet.recording`).  Exits 0 when the run is over or on SIGINT/SIGTERM, after writing
the file's summary and footer.  It is the same for every scenario kind.  Restarted (``network.
restart: on-failure``), it continues in the next segment, ``FILE.2.mcap``, ... (the replay reads
them in order).
"""

from __future__ import annotations

import sys
from pathlib import Path

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
from covnet.recording import RecordingWriter, next_segment, run_metadata
from recorder import node


def main(argv: list[str] | None = None) -> int:
    p = common_parser("recorder", "The recorder process: every message of the run to MCAP.")
    p.add_argument("--connect", help="router endpoint (default: the config's network)")
    p.add_argument("--out", required=True, help="MCAP file to write (e.g. RUN_DIR/recording.mcap)")
    args = p.parse_args(argv)

    def body() -> int:
        stop = stop_on_signals()
        _, cfg = load_config(args)
        resolve_run(args, cfg)
        out = next_segment(Path(args.out))  # a restarted recorder never overwrites
        out.parent.mkdir(parents=True, exist_ok=True)
        with open_client(args, cfg.network, node.ROLE, node.NODE_ID, stop) as bus:
            with RecordingWriter(out, run_id=args.run, metadata=run_metadata(args.run, cfg)) as w:
                counts = node.run(cfg, bus, args.run, WallClock(args.speed), stop, w)
        print(f"stopped: {w.messages} messages recorded to {out}; {dict(counts)}")
        return EXIT_OK

    return guarded(body, "recorder")


if __name__ == "__main__":
    sys.exit(main())
