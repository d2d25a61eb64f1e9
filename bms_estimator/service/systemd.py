"""sd_notify(3) without dependencies.

Sends ``READY=1``, ``WATCHDOG=1``, ``STOPPING=1``, ``RELOADING=1``, ``STATUS=...`` datagrams
to ``$NOTIFY_SOCKET`` (a filesystem path or, with a leading ``@``, an
abstract-namespace socket). Every function is a no-op returning ``False``
when the variable is unset and never raises.

With ``Type=notify`` + ``WatchdogSec=`` in the unit, run
:func:`watchdog_loop` as a task: it pings ``WATCHDOG=1`` every
``watchdog_interval_s()`` (half of ``$WATCHDOG_USEC``) *only while the
estimator heartbeat is fresh*, so a stalled estimator loop gets the service
restarted by systemd.
"""

from __future__ import annotations

import asyncio
import os
import socket
import time
from collections.abc import Mapping
from typing import Protocol

import structlog

__all__ = [
    "notify",
    "notify_ready",
    "notify_reloading",
    "notify_status",
    "notify_stopping",
    "notify_watchdog",
    "watchdog_interval_s",
    "watchdog_loop",
]

log = structlog.get_logger("bms.systemd")


class _Fresh(Protocol):
    def is_fresh(self) -> bool: ...


def _address(env: Mapping[str, str]) -> str | bytes | None:
    addr = env.get("NOTIFY_SOCKET", "")
    if not addr:
        return None
    if addr.startswith("@"):
        # Abstract namespace: leading NUL instead of '@'.
        return b"\0" + addr[1:].encode()
    if addr.startswith("/"):
        return addr
    return None  # vsock (vsock:CID:PORT) and relative paths are not supported


def notify(*lines: str, env: Mapping[str, str] | None = None) -> bool:
    """Send ``lines`` (``"KEY=value"``) as one datagram. True when sent."""
    env = os.environ if env is None else env
    addr = _address(env)
    if addr is None or not lines:
        return False
    payload = "\n".join(lines).encode("utf-8", "replace")
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.sendto(payload, addr)
        return True
    except OSError as exc:
        log.debug("sd_notify failed", error=str(exc))
        return False


def _status_line(status: str) -> str:
    # STATUS= is single-line.
    return "STATUS=" + " ".join(str(status).splitlines())


def notify_ready(status: str | None = None, *, env: Mapping[str, str] | None = None) -> bool:
    lines = ["READY=1"]
    if status:
        lines.append(_status_line(status))
    return notify(*lines, env=env)


def notify_watchdog(*, env: Mapping[str, str] | None = None) -> bool:
    return notify("WATCHDOG=1", env=env)


def notify_stopping(status: str | None = None, *, env: Mapping[str, str] | None = None) -> bool:
    lines = ["STOPPING=1"]
    if status:
        lines.append(_status_line(status))
    return notify(*lines, env=env)


def notify_reloading(status: str | None = None, *, env: Mapping[str, str] | None = None) -> bool:
    """``RELOADING=1`` with ``MONOTONIC_USEC`` (what systemd >= 253 asks of a reload); ``READY=1`` ends it."""
    lines = ["RELOADING=1", f"MONOTONIC_USEC={time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000}"]
    if status:
        lines.append(_status_line(status))
    return notify(*lines, env=env)


def notify_status(status: str, *, env: Mapping[str, str] | None = None) -> bool:
    return notify(_status_line(status), env=env)


def watchdog_interval_s(env: Mapping[str, str] | None = None) -> float | None:
    """Half of ``$WATCHDOG_USEC`` in seconds, or None when no watchdog applies.

    ``$WATCHDOG_PID``, when set, must be this process.
    """
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC", "")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID", "")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            return None
    try:
        value = int(usec)
    except ValueError:
        return None
    if value <= 0:
        return None
    return value / 2 / 1e6


async def watchdog_loop(
    heartbeat: _Fresh | None = None,
    *,
    interval_s: float | None = None,
    env: Mapping[str, str] | None = None,
) -> None:
    """Ping the systemd watchdog until cancelled.

    Pings only while ``heartbeat.is_fresh()`` (if given). Returns at once
    when no watchdog is configured (``interval_s`` None and no
    ``$WATCHDOG_USEC``).
    """
    interval = interval_s if interval_s is not None else watchdog_interval_s(env)
    if interval is None:
        return
    warned = False
    while True:
        if heartbeat is None or heartbeat.is_fresh():
            notify_watchdog(env=env)
            warned = False
        elif not warned:
            log.warning("estimator heartbeat stale: withholding systemd watchdog ping")
            warned = True
        await asyncio.sleep(interval)
