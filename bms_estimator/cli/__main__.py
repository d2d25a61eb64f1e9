"""``bms-estimator`` command line: one subcommand per module, as in cantools."""

from __future__ import annotations

import argparse
import importlib
import sys

from ..data import DataError

#: subcommand name -> module in this package (each has ``add_parser`` and ``run``)
SUBCOMMANDS = {
    "ocv": "ocv",
    "fit": "fit",
    "compare": "compare",
    "soc": "soc",
    "bench": "bench",
    "demo": "demo",
    "diagnose": "diagnose",
    "encode-log": "encode_log",
    "replay": "replay",
    "dashboard": "dashboard",
    "run": "run",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bms-estimator",
        description="Online battery ECM identification (continuous-time LIF) and SOC estimation.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in SUBCOMMANDS.items():
        mod = importlib.import_module(f"{__package__}.{module}")
        mod.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # diagnostics go to stderr, so that stdout stays the command's output (JSON, tables)
    from ..service.logging import configure_logging

    configure_logging(level="WARNING", fmt="console", stream=sys.stderr)
    try:
        return int(args.func(args) or 0)
    except (DataError, ValueError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        print(f"bms-estimator {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
