"""``bms-estimator replay``: send a CAN log onto a bus, paced by its own timestamps."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import can.cli as can_cli


def add_parser(sub) -> None:
    p = sub.add_parser(
        "replay",
        help="replay a CAN log (.log/.asc/.blf) onto a bus at any speed",
        description="Sends every frame at t0_wall + (t_frame - t0_log) / SPEED. Receivers see the LOG's timestamps "
                    "on 'virtual' (in-process) and on 'udp_multicast' when they receive with "
                    "bms_estimator.replay.replay.LogTimeUdpMulticastBus; on socketcan the kernel stamps frames on "
                    "reception, so only --speed 1 keeps the recording's timing. Details: "
                    "bms_estimator/replay/replay.py.",
    )
    p.add_argument("log", type=Path, help="candump .log, Vector .asc or .blf file")
    # python-can's own bus options (-i/-c/-b/--fd/--data-bitrate/--timing/--bus-kwargs); what is
    # not given comes from python-can's configuration ($CAN_INTERFACE, $CAN_CHANNEL, ~/.canrc, ...)
    can_cli.add_bus_arguments(p, group_title="bus (python-can; unset options come from CAN_INTERFACE, "
                                             "CAN_CHANNEL, ~/.canrc)")
    p.add_argument("--port", type=int, default=None, help="udp_multicast port (default python-can's 43113)")
    p.add_argument("--speed", default="1", help="factor on real time (1 = real time, 50 = 50x) or 'max' (default 1)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..replay.replay import bus_config_from_args, log_span, open_replay_bus, parse_speed, read_log, replay_messages

    speed = parse_speed(args.speed)
    messages = read_log(args.log)
    interface, channel, kwargs = bus_config_from_args(args)
    if args.port is not None:
        kwargs["port"] = args.port
    bus = open_replay_bus(interface, channel, **kwargs)
    bar = None
    progress = None
    if sys.stderr.isatty() and not args.no_progress:
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        span = log_span(args.log)
        total = (span[1] - span[0]) if span else None
        bar = Progress(
            TextColumn("{task.description}"), BarColumn(),
            TextColumn("{task.completed:,.0f}/{task.total:,.0f} log s" if total else "{task.completed:,.0f} log s"),
            TextColumn("{task.fields[frames]:,} frames"), TimeElapsedColumn(), TimeRemainingColumn(),
            console=Console(stderr=True), transient=False,
        )
        task = bar.add_task(f"replay {args.log.name} x{args.speed}", total=total, frames=0)

        def advance(sent: int, log_s: float) -> None:
            bar.update(task, completed=log_s, frames=sent)

        progress = advance

        bar.start()
    try:
        stats = replay_messages(messages, bus, speed, progress)
    finally:
        if bar is not None:
            bar.stop()
        bus.shutdown()
    eff = stats.effective_speed
    print(f"{args.log}: {stats.sent} frames, {stats.log_duration_s:.1f} log s in {stats.wall_s:.1f} s "
          f"({'instant' if eff == float('inf') else f'{eff:.1f}x'}), {stats.send_errors} dropped")
    return 0 if stats.send_errors == 0 else 1
