"""`lca-can-server`: relay CAN frames between processes or machines, as one bus.

    lca-can-server --port 54701                                  # terminal 1
    lca-virtual-drive --interface lca_remote --channel ws://127.0.0.1:54701/   # terminal 2

Exit codes: 0 on a clean stop (SIGINT, SIGTERM), 2 if it cannot bind. docs/can-transport.md.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from lca_sim.canbus.relay import RelayServer
from lca_sim.canbus.remote import INTERFACE_NAME
from lca_sim.canbus.wire import DEFAULT_HOST, DEFAULT_PORT
from lca_sim.errors import EXIT_OK, fail
from lca_sim.runtime import stop_signals


def _port(text: str) -> int:
    """A TCP port, 0-65535 (0: any free one)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a TCP port (0-65535), got {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"expected a TCP port (0-65535), got {port}")
    return port


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
        "--port",
        type=_port,
        default=DEFAULT_PORT,
        help=f"TCP port, 0 = any (default {DEFAULT_PORT})",
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
        return fail("lca-can-server", f"cannot listen on {args.host}:{args.port}: {exc}")
    with stop_signals(lambda _name: server.stop()):
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
