"""``bms-estimator run --config FILE``: the estimator daemon (see bms_estimator/service/daemon.py).

Exit codes: 0 after SIGTERM/SIGINT (state saved, ``offline`` published),
2 for a configuration problem (one line per problem on stderr), 1 if the
daemon failed unexpectedly. SIGHUP reloads the configuration file
(:func:`bms_estimator.service.daemon.serve`): one that does not validate is
logged and the service goes on with the one it has.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import signal
import sys
from pathlib import Path

import structlog


def freeze_long_lived() -> None:
    """Keep what lives for ever out of the cyclic GC: the DBC and the decoder's per-multiplexer plan
    are large, and full collections over them would stall a tick for ~100 ms every few seconds.

    Called at start and after each reload.  It unfreezes first: after a reload the service that ran
    before is garbage, and frozen its reference cycles would never be collected (one service's
    worth of memory kept for good per reload)."""
    gc.unfreeze()
    gc.collect()
    gc.freeze()


def add_parser(sub) -> None:
    p = sub.add_parser(
        "run",
        help="run the estimator daemon (CAN in, CAN + MQTT out; systemd Type=notify)",
        description="Run the estimator service until SIGTERM/SIGINT; SIGHUP reloads the configuration "
        "(an invalid one is logged and the running one kept). Configuration: TOML file plus "
        "BMS_<SECTION>__<KEY> environment overrides (see deploy/config.example.toml).",
    )
    p.add_argument("--config", type=Path, default=None,
                   help="TOML configuration file (default: built-in defaults + environment)")
    p.add_argument("--log-format", choices=("auto", "json", "console"), default=None,
                   help="override logging.format (auto: JSON under systemd, text in a terminal)")
    p.add_argument("--log-level", choices=("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"), default=None,
                   type=str.upper, help="override logging.level")
    p.add_argument("--check-config", action="store_true",
                   help="load and check the configuration (DBC, mapping, OCV table, estimator parameters), then exit")
    p.set_defaults(func=run)


def _config_error(exc) -> int:
    print(f"bms-estimator run: {exc.header}", file=sys.stderr)
    for problem in exc.problems:
        print(f"  {problem}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from ..service.config import ConfigError, load_config
    from ..service.daemon import Service, serve
    from ..service.logging import configure_logging

    # A SIGHUP before the loop's handler is installed (the configuration, DBC and OCV table take about
    # a second to load) would end the process, and systemd counts that as a clean exit (no restart):
    # hold it, and reload once the service runs.
    early_hup: list[int] = []
    signal.signal(signal.SIGHUP, lambda signum, _frame: early_hup.append(signum))
    try:
        cfg = load_config(args.config)
        configure_logging(args.log_level or cfg.logging.level, args.log_format or cfg.logging.format)
        service = Service(cfg)  # checks DBC, mapping, OCV, estimator parameters; opens nothing
    except ConfigError as exc:
        return _config_error(exc)
    if args.check_config:
        absent = cfg.can.channel_problem()
        if absent is not None:  # not an error: the service starts with CAN down and opens it when it appears
            print(f"configuration valid, but can.channel: {absent}: the service would start with CAN down "
                  "and receive nothing until it appears", file=sys.stderr)
        else:
            print("configuration ok", file=sys.stderr)
        return 0

    freeze_long_lived()
    # The CAN receive thread must get the GIL back quickly while a tick computes: each frame it
    # reads releases the GIL for the syscall and then waits up to the switch interval for it
    # (5 ms by default, i.e. ~200 frames/s during a tick against a bus of 7,400/s).
    sys.setswitchinterval(0.0005)
    log = structlog.get_logger("bms.cli")
    log.info("starting", config=str(args.config) if args.config else None, settings=cfg.redacted())

    def rebuild() -> Service:  # SIGHUP: the configuration as it is now (raises ConfigError naming each problem)
        return Service(load_config(args.config))

    def reloaded(new: Service) -> None:
        configure_logging(args.log_level or new.cfg.logging.level, args.log_format or new.cfg.logging.format)
        freeze_long_lived()  # the new service's DBC and plan; the old one's collected

    async def main() -> None:
        stop, reload = asyncio.Event(), asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig, event in ((signal.SIGTERM, stop), (signal.SIGINT, stop), (signal.SIGHUP, reload)):
            try:
                loop.add_signal_handler(sig, event.set)
            except (NotImplementedError, RuntimeError):  # pragma: no cover - not on Unix
                signal.signal(sig, lambda *_, e=event: loop.call_soon_threadsafe(e.set))
        if early_hup:
            reload.set()
        await serve(service, stop, reload, rebuild, config=str(args.config) if args.config else None,
                    reloaded=reloaded)

    try:
        asyncio.run(main())
    except KeyboardInterrupt:  # pragma: no cover - the handler above sets the stop event instead
        return 0
    except Exception:
        log.exception("service failed")
        return 1
    return 0
