"""``bms-estimator`` command line: one subcommand per module, as in cantools."""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from .. import package_version
from ..errors import EXIT_DATA, EXIT_RUNTIME, EXIT_USAGE, BmsEstimatorError, one_line_error

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
    "batch": "batch",
    "sop-backtest": "sop_backtest",
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole command line, or (``command`` given, one of :data:`SUBCOMMANDS`) only that
    subcommand's parser: each module imports what its command needs (python-can, scipy, Dask), so
    ``bms-estimator soc ...`` does not pay for ``batch``'s imports."""
    parser = argparse.ArgumentParser(
        prog="bms-estimator",
        description="Online battery ECM identification (continuous-time LIF) and SOC estimation.",
        epilog="Exit codes: 0 done, 1 runtime failure (CAN bus, broker, service), 2 bad command line or "
               "configuration, 3 unreadable or malformed input data.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in SUBCOMMANDS.items():
        if command is None or name == command:
            importlib.import_module(f"{__package__}.{module}").add_parser(sub)
    return parser


def _command(argv: list[str]) -> str | None:
    """The subcommand named first on the command line, if it is one (else None: the whole parser, which
    then lists them or names the unknown one)."""
    first = next((a for a in argv if not a.startswith("-")), None)
    return first if first in SUBCOMMANDS else None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_command(argv))
    args = parser.parse_args(argv)
    # diagnostics go to stderr, so that stdout stays the command's output (JSON, tables)
    from ..service.logging import configure_logging

    configure_logging(level="WARNING", fmt="console", stream=sys.stderr)
    where = f"bms-estimator {args.command}"

    def one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
        # a warning is for the user: one line, without the source line Python would quote
        print(f"{where}: warning: {message}", file=sys.stderr if file is None else file)

    try:
        with warnings.catch_warnings():  # restores the previous hook when the command returns
            warnings.showwarning = one_line_warning
            return int(args.func(args) or 0)
    except BmsEstimatorError as exc:
        print(f"{where}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except BrokenPipeError as exc:
        if _stdout_is_closed():
            return _quiet_stdout()
        print(f"{where}: error: {one_line_error(exc)}", file=sys.stderr)  # (a socket's: the broker, a CAN gateway)
        return EXIT_RUNTIME
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError, EOFError) as exc:
        # an input file that cannot be read: "PATH: reason", not Python's "[Errno 2] ... 'PATH'"
        text = f"{exc.filename}: {exc.strerror}" if getattr(exc, "filename", None) and exc.strerror else exc
        print(f"{where}: error: {text}", file=sys.stderr)
        return EXIT_DATA
    except MemoryError as exc:  # an input too large for this machine: one line, not numpy's traceback
        print(f"{where}: error: out of memory{': ' + str(exc) if str(exc) else ''}", file=sys.stderr)
        return EXIT_RUNTIME
    except ValueError as exc:  # an option value the commands or the core refuse
        print(f"{where}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as exc:  # python-can's bus errors are not all OSErrors; imported only by the commands using it
        can = sys.modules.get("can")
        if not isinstance(exc, OSError) and not (can is not None and isinstance(exc, can.CanError)):
            raise
        print(f"{where}: error: {one_line_error(exc)}", file=sys.stderr)
        return EXIT_RUNTIME
    except KeyboardInterrupt:
        return 130



#: the exit status of a command whose reader closed its standard output (128 + SIGPIPE, as a shell reports it)
EXIT_STDOUT_CLOSED = 141


def _stdout_is_closed() -> bool:
    """Whether standard output's reader went away: its pipe reports an error to ``poll``."""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLERR)
        return any(event & select.POLLERR for _, event in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # (no poll on this platform, or a stdout without a descriptor)
        return False


def _quiet_stdout() -> int:
    """The reader of standard output went away (``--json - | head``): nothing more to say, and no error. It printed
    'error: BrokenPipeError: [Errno 32] Broken pipe', exit 1, and Python's 'Exception ignored ... BrokenPipeError'
    at exit; standard output now goes to ``/dev/null`` so that the interpreter's final flush does not fail again."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # (a stdout without a file descriptor: nothing to flush)
        pass
    return EXIT_STDOUT_CLOSED


if __name__ == "__main__":
    sys.exit(main())
