"""structlog setup for the service.

* JSON lines (one object per line) under systemd/journald (``JOURNAL_STREAM``
  or ``INVOCATION_ID`` in the environment) or when ``format = "json"``;
* readable console output otherwise (colours only on a TTY).

The standard-library ``logging`` records of libraries (paho/aiomqtt,
python-can, asyncio) are routed through the same renderer, so the journal
holds one uniform stream. When stderr *is* the journal stream
(``JOURNAL_STREAM`` matches its device/inode), each JSON line is prefixed with
the syslog priority ``<N>`` that journald strips and uses as the entry's
priority.

``configure_logging`` may be called again (tests, reload); it replaces the
handler it installed before.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping
from typing import IO, Any, Literal

import structlog

__all__ = ["configure_logging", "detect_format", "get_logger", "under_systemd"]

_HANDLER_TAG = "_bms_estimator_handler"

# syslog priorities for journald's "<N>" line prefix (SyslogLevelPrefix=yes).
_SYSLOG_PRIORITY = {
    "critical": 2,
    "exception": 3,
    "error": 3,
    "warning": 4,
    "warn": 4,
    "info": 6,
    "debug": 7,
    "notset": 7,
}


def under_systemd(env: Mapping[str, str] | None = None) -> bool:
    """True when started by systemd (journald stream or a unit invocation)."""
    env = os.environ if env is None else env
    return bool(env.get("JOURNAL_STREAM") or env.get("INVOCATION_ID"))


def detect_format(
    requested: str = "auto", env: Mapping[str, str] | None = None
) -> Literal["json", "console"]:
    """Resolve ``auto`` to ``json`` under systemd, else ``console``."""
    if requested == "json":
        return "json"
    if requested == "console":
        return "console"
    return "json" if under_systemd(env) else "console"


def _stream_is_journal(stream: IO[str], env: Mapping[str, str]) -> bool:
    js = env.get("JOURNAL_STREAM", "")
    if not js:
        return False
    try:
        dev_s, ino_s = js.split(":", 1)
        st = os.fstat(stream.fileno())
        return st.st_dev == int(dev_s) and st.st_ino == int(ino_s)
    except (ValueError, OSError, AttributeError, TypeError):
        return False


class _JournalPrefixRenderer:
    """Wrap a renderer and prefix ``<priority>`` for journald."""

    def __init__(self, inner: Any) -> None:
        self._inner = inner

    def __call__(self, logger: Any, method_name: str, event_dict: dict[str, Any]) -> str:
        level = str(event_dict.get("level", method_name)).lower()
        prio = _SYSLOG_PRIORITY.get(level, 6)
        return f"<{prio}>{self._inner(logger, method_name, event_dict)}"


def configure_logging(
    level: str = "INFO",
    fmt: str = "auto",
    *,
    stream: IO[str] | None = None,
    env: Mapping[str, str] | None = None,
) -> Literal["json", "console"]:
    """Configure structlog and the stdlib root logger; return the chosen format.

    ``level``/``fmt`` are usually ``cfg.logging.level`` / ``cfg.logging.format``.
    ``stream`` defaults to ``sys.stderr``; ``env`` to ``os.environ``.
    """
    env = os.environ if env is None else env
    stream = sys.stderr if stream is None else stream
    chosen = detect_format(fmt, env)
    numeric_level = logging.getLevelName(str(level).upper())
    if not isinstance(numeric_level, int):
        numeric_level = logging.INFO

    timestamper = structlog.processors.TimeStamper(fmt="iso", utc=True)
    shared: list[Any] = [
        structlog.contextvars.merge_contextvars,
        structlog.stdlib.add_log_level,
        structlog.stdlib.add_logger_name,
        structlog.stdlib.PositionalArgumentsFormatter(),
        timestamper,
        structlog.processors.StackInfoRenderer(),
    ]

    renderer: Any
    if chosen == "json":
        renderer = structlog.processors.JSONRenderer(sort_keys=False, default=str)
        # Structured tracebacks without local variables (they may hold secrets).
        exc_renderer = structlog.processors.ExceptionRenderer(
            structlog.tracebacks.ExceptionDictTransformer(show_locals=False)
        )
        final: list[Any] = [exc_renderer, structlog.processors.UnicodeDecoder()]
        if _stream_is_journal(stream, env):
            renderer = _JournalPrefixRenderer(renderer)
    else:
        try:
            colors = bool(stream.isatty())
        except (AttributeError, ValueError):
            colors = False
        # plain_traceback: never print local variables (they may hold secrets).
        renderer = structlog.dev.ConsoleRenderer(
            colors=colors, exception_formatter=structlog.dev.plain_traceback
        )
        final = []

    structlog.configure(
        processors=[
            structlog.stdlib.filter_by_level,
            *shared,
            structlog.stdlib.ProcessorFormatter.wrap_for_formatter,
        ],
        logger_factory=structlog.stdlib.LoggerFactory(),
        wrapper_class=structlog.stdlib.BoundLogger,
        cache_logger_on_first_use=False,
    )

    formatter = structlog.stdlib.ProcessorFormatter(
        foreign_pre_chain=shared,
        processors=[
            structlog.stdlib.ProcessorFormatter.remove_processors_meta,
            *final,
            renderer,
        ],
    )
    handler = logging.StreamHandler(stream)
    handler.setFormatter(formatter)
    setattr(handler, _HANDLER_TAG, True)

    root = logging.getLogger()
    for old in list(root.handlers):
        if getattr(old, _HANDLER_TAG, False):
            root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(numeric_level)
    # paho logs every packet at DEBUG; keep it quiet unless asked for.
    logging.getLogger("mqtt").setLevel(max(numeric_level, logging.INFO))
    return chosen


def get_logger(name: str | None = None, **initial: Any) -> Any:
    """A structlog logger bound to ``initial`` values."""
    return structlog.get_logger(name, **initial)
