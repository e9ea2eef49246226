"""``python -m covnet.processes.netem``: hold one emulated link up until Ctrl-C (or SIGTERM).

::

    python -m covnet.processes.netem --ns-a NS_A --ns-b NS_B --config link.yaml [--seed 0] [--mode
    auto]
    python -m covnet.processes.netem --create --config link.yaml      # make (and later delete) the
    two
                                                            # namespaces as well

``link.yaml`` holds the two directions as :meth:`covnet.core.delay.LinkSpec.from_dict` reads
them; a missing direction is ideal::

    a_to_b: {delay: {kind: constant, value_s: 0.020}, jitter_s: 0.002, loss: 0.01}
    b_to_a: {delay: {kind: uniform, low_s: 0.004, high_s: 0.006}, reorder: 1.0}

Once the link is up, one JSON line describes it (namespaces, addresses, devices, mode, forwarder
pid); run programs on either side with ``ip netns exec NS ...``.  On exit everything is removed
and the forwarder's counters are printed as a second JSON line.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import signal
import sys
from pathlib import Path
from typing import Any

import yaml

from covnet.core.delay import LinkSpec
from covnet.processes.netem.link import MODES, emulated_link, namespaces


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m covnet.processes.netem", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("--config", required=True, type=Path, help="YAML with a_to_b and b_to_a")
    p.add_argument("--ns-a", help="existing namespace of side a")
    p.add_argument("--ns-b", help="existing namespace of side b")
    p.add_argument("--create", action="store_true", help="make two namespaces for the link")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--link-index", type=int, default=0)
    p.add_argument("--mode", choices=MODES, default="auto")
    p.add_argument("--subnet", default="10.77.0.0/30")
    args = p.parse_args(argv)
    if (
        args.create == bool(args.ns_a or args.ns_b)
        or not args.create
        and not (args.ns_a and args.ns_b)
    ):
        p.error("give either --ns-a and --ns-b, or --create")
    data = yaml.safe_load(args.config.read_text()) or {}
    unknown = set(data) - {"a_to_b", "b_to_a"}
    if unknown:
        p.error(f"{args.config}: unknown keys {sorted(unknown)}; expected a_to_b, b_to_a")
    try:
        specs = [LinkSpec.from_dict(data.get(k) or {}) for k in ("a_to_b", "b_to_a")]
    except ValueError as exc:
        p.error(f"{args.config}: {exc}")
    for sig in (signal.SIGINT, signal.SIGTERM):  # SIGINT too: a background job ignores it
        signal.signal(sig, _interrupt)
    with contextlib.ExitStack() as stack:
        ns = stack.enter_context(namespaces(2)) if args.create else [args.ns_a, args.ns_b]
        info = stack.enter_context(
            emulated_link(ns[0], ns[1], specs[0], specs[1], args.seed, mode=args.mode,
                          link_index=args.link_index, subnet=args.subnet)
        )  # fmt: skip
        print(json.dumps(dataclasses.asdict(info)), flush=True)
        try:
            while True:
                signal.pause()
        except KeyboardInterrupt:
            pass
    print(json.dumps({"stats": info.stats}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
