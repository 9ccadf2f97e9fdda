"""`lca-can-server`: relay CAN frames between processes or machines, as one bus.

    lca-can-server --port 54701                                  # terminal 1
    lca-virtual-drive --interface lca_remote --channel ws://127.0.0.1:54701/   # terminal 2

Exit codes: 0 on a clean stop (SIGINT, SIGTERM), 2 if it cannot bind. docs/can-transport.md.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from collections.abc import Sequence
from types import FrameType

from lca_sim.canbus.relay import RelayServer
from lca_sim.canbus.remote import INTERFACE_NAME
from lca_sim.canbus.wire import DEFAULT_HOST, DEFAULT_PORT
from lca_sim.errors import EXIT_BAD_INPUT, EXIT_OK


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="lca-can-server",
        description=(
            "Relay CAN frames between processes or machines, as one bus (python-can-remote's "
            f"websocket protocol). Clients: python-can interface {INTERFACE_NAME!r}, channel "
            "ws://HOST:PORT/. Runs until SIGINT or SIGTERM."
        ),
    )
    parser.add_argument(
        "--host",
        default=DEFAULT_HOST,
        help=f"address to bind (default {DEFAULT_HOST}; 0.0.0.0 exposes it to the network)",
    )
    parser.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"TCP port, 0 = any (default {DEFAULT_PORT})"
    )
    parser.add_argument(
        "--log-level", default="warning", choices=("debug", "info", "warning", "error")
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the relay until SIGINT/SIGTERM; 0 on a clean stop, 2 if it cannot bind."""
    args = _parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    try:
        server = RelayServer(args.host, args.port)
    except OSError as exc:
        print(
            f"lca-can-server: error: cannot listen on {args.host}:{args.port}: {exc}",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT

    def on_signal(signum: int, frame: FrameType | None) -> None:
        server.stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    print(
        f"lca-can-server: relaying on {server.url}; SIGINT or SIGTERM stops",
        file=sys.stderr,
        flush=True,
    )
    server.serve()
    print(f"lca-can-server: stopped; {server.stats}", file=sys.stderr, flush=True)
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
