"""``bms-estimator dashboard``: live terminal view of the service's MQTT topics."""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import sys
import time

from ..errors import EXIT_RUNTIME, DataError
from .common import positive_float


def pack_id(text: str) -> str:
    """``--pack``: a pack id as the service's ``pack.pack_id`` takes it (one MQTT topic level, no wildcard)."""
    from ..service.config import ID_PATTERN

    if not re.fullmatch(ID_PATTERN, text):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a pack id: a letter or digit, then up to 63 letters, digits, '_', '.' or '-' "
            "(as the service's pack.pack_id; no '/' and no MQTT wildcard '+' or '#')")
    return text


def base_topic(text: str) -> str:
    """``--base-topic``: a topic prefix as the service's ``mqtt.base_topic`` takes it."""
    from ..service.config import check_topic_part

    try:
        return check_topic_part(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text!r} {exc} (as the service's mqtt.base_topic)") from None


def add_parser(sub) -> None:
    p = sub.add_parser(
        "dashboard",
        help="live per-cell table of the estimator service's MQTT output (any broker)",
        description="Subscribes to <base>/<pack>/cell/+/state, <base>/<pack>/pack/state and "
                    "<base>/<pack>/availability and shows SOC, R0, tau1, tau2, c0, the stale flag and the age of "
                    "each cell's last message. Unknown topics and garbage payloads are ignored and counted.",
    )
    p.add_argument("--broker", default="localhost:1883", help="HOST[:PORT] of the MQTT broker (default localhost:1883)")
    p.add_argument("--pack", type=pack_id, default=None, help="pack id to show (default: every pack seen)")
    p.add_argument("--base-topic", type=base_topic, default="bms",
                   help="topic prefix of the service (default bms)")
    p.add_argument("--username", default=None)
    p.add_argument("--password-env", default=None, metavar="VAR",
                   help="name of an environment variable holding the password (not on the command line)")
    p.add_argument("--tls", action="store_true", help="connect with TLS (system CA store)")
    p.add_argument("--ca-file", default=None, help="CA certificate for --tls")
    p.add_argument("--duration-s", type=positive_float, default=None, help="exit after S seconds")
    p.add_argument("--refresh-hz", type=positive_float, default=4.0, help="screen refreshes per second (default 4)")
    p.add_argument("--stale-after-s", type=positive_float, default=5.0,
                   help="highlight cells whose last message is older than this (default 5 s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    return asyncio.run(_main(args))


async def _main(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.live import Live

    from ..replay.dashboard import DashboardState, parse_broker, render, run_dashboard

    host, port = parse_broker(args.broker)
    password = None
    if args.password_env:
        password = os.environ.get(args.password_env)
        if password is None:
            raise ValueError(f"--password-env: environment variable {args.password_env} is not set")
    tls = None
    if args.tls or args.ca_file:
        import ssl

        try:
            tls = ssl.create_default_context(cafile=args.ca_file)
        except ssl.SSLError as exc:  # (its message names neither the option nor the file)
            raise DataError(f"--ca-file {args.ca_file}: not a CA certificate in PEM format "
                            f"({exc.reason or exc})") from None
        except OSError as exc:
            raise DataError(f"--ca-file {args.ca_file}: {(exc.strerror or str(exc)).lower()}") from None
    state = DashboardState(args.pack, args.base_topic)
    console = Console()

    def view():
        state.tick(time.monotonic())
        rows = max(5, console.size.height - 6 - 2 * max(1, len(state.packs)))
        return render(state, max_rows=rows, stale_after_s=args.stale_after_s)

    stop = asyncio.Event()
    sub = asyncio.create_task(run_dashboard(state, host, port, username=args.username, password=password,
                                            tls_context=tls, duration_s=args.duration_s, stop=stop))
    period = 1.0 / args.refresh_hz
    if not console.is_terminal:  # piped: one final snapshot
        try:
            await sub
        finally:
            console.print(view())
        return _outcome(state)
    with Live(view(), console=console, auto_refresh=False, vertical_overflow="crop") as live:
        try:
            while not sub.done():
                live.update(view(), refresh=True)
                await asyncio.wait({sub}, timeout=period)
            sub.result()
        finally:
            stop.set()
            if not sub.done():
                sub.cancel()
            live.update(view(), refresh=True)
    return _outcome(state)


def _outcome(state) -> int:
    """0 when the broker was reached; else the runtime-failure code with one line saying why."""
    if state.ever_connected:
        return 0
    why = f" ({state.last_error})" if state.last_error else ""
    where = f" at {state.broker}" if state.broker else ""
    print(f"bms-estimator dashboard: error: never connected to the broker{where}{why}", file=sys.stderr)
    return EXIT_RUNTIME
