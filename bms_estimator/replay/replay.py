"""Replay a CAN log onto a bus, paced by the log's own timestamps (``bms-estimator replay``).

Pacing
------
Message ``m`` is sent when the wall clock reaches
``t0_wall + (m.timestamp - t0_log) / speed`` (``t0_*`` = the first message), so the
schedule never drifts however long the log is; a sender that falls behind (a slow
bus, a high speed) sends at once until it has caught up. ``speed="max"`` (or
``inf``) never sleeps. Logs: candump ``.log``, Vector ``.asc`` and ``.blf``
(python-can's ``can.LogReader``; ``.gz`` variants too).

Timestamps: what the receiver sees
----------------------------------
The estimator service builds its samples on FRAME time (``msg.timestamp``; see
``bms_estimator.can.sampler``), so its results are identical at any replay speed
exactly when the receiver sees the LOG's timestamps. The replayer always sends the
log's message objects with ``timestamp`` = the log time; whether that reaches the
receiver depends on the interface:

``virtual`` (python-can, in one process)
    The SENDING bus decides: ``VirtualBus(preserve_timestamps=True)`` hands every
    receiver a copy with the sender's ``timestamp``, otherwise ``time.time()``.
    :func:`open_replay_bus` opens the sender with ``preserve_timestamps=True``, so
    any receiver on the channel (a plain ``can.Bus(interface="virtual", channel=C)``,
    the service's ``ResilientBus``) gets the log time, at any speed.
``udp_multicast`` (between processes)
    The frame's timestamp travels in the datagram (msgpack), but python-can's
    ``UdpMulticastBus`` REPLACES it by the socket's receive time. A receiver that
    wants the log time opens :class:`LogTimeUdpMulticastBus` instead (same
    arguments; it keeps the sender's timestamp) - for the service:
    ``Service(cfg, bus_factory=open_bus_log_time)`` (or ``ResilientBus(cfg,
    bus_factory=open_bus_log_time)``). Datagrams can be lost when the receiver
    falls behind (socket buffers): prefer a finite speed.
``socketcan`` (vcan/can)
    The kernel stamps every frame on reception; the log time cannot be carried.
    The service then sees the replay's pacing, so only ``--speed 1`` reproduces
    the recording's timing (faster replays compress the service's time axis).

The message's ``channel`` is cleared before sending (socketcan would otherwise
send a frame logged on ``can1`` to the interface ``can1``).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from ..errors import CanBusError, DataError, UsageError, one_line_error
from ..fleet.frames import check_log_complete

__all__ = [
    "bus_config_from_args",
    "LOG_SUFFIXES",
    "LogTimeUdpMulticastBus",
    "ReplayStats",
    "log_span",
    "open_bus_log_time",
    "open_replay_bus",
    "parse_speed",
    "read_log",
    "replay_messages",
]

LOG_SUFFIXES = (".log", ".asc", ".blf")


def parse_speed(text: str | float) -> float:
    """``"max"``/``"inf"`` -> ``math.inf``; otherwise a positive finite factor (1 = real time)."""
    if isinstance(text, str):
        t = text.strip().lower()
        if t in ("max", "inf", "infinity"):
            return math.inf
        try:
            value = float(t.rstrip("x"))
        except ValueError:
            raise ValueError(f"speed {text!r}: give a positive factor (1 = real time) or 'max'") from None
    else:
        value = float(text)
    if math.isnan(value) or value <= 0:
        raise ValueError(f"speed {text!r} must be > 0 (or 'max')")
    return value


# ------------------------------------------------------------------- reading
def _log_suffix(path: Path) -> str:
    suffixes = [s.lower() for s in path.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes = suffixes[:-1]
    return suffixes[-1] if suffixes else ""


def read_log(path: str | Path) -> Iterator[can.Message]:
    """Messages of a candump ``.log``, ``.asc`` or ``.blf`` file (``can.LogReader``), lazily.

    A truncated ``.blf``, ``.asc`` or candump ``.log`` raises :class:`DataError` at once (the
    checks of ``batch``); a file the reader cannot parse, or one without a frame, when the iteration
    reaches the fault, naming the file and how many frames came before it.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: a directory, not a log file")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such log file")
    if _log_suffix(path) not in LOG_SUFFIXES:
        raise ValueError(f"{path}: replay reads {', '.join(LOG_SUFFIXES)} logs (by suffix)")
    try:
        # python-can stops quietly at the cut of a truncated .blf/.asc and sends a cut .log line's frame, shortened
        check_log_complete(path, _log_suffix(path))
        reader = can.LogReader(str(path))
    except DataError:
        raise
    except Exception as exc:  # noqa: BLE001 - a .blf reader parses its header here
        raise DataError(f"{path}: unreadable as a CAN log ({one_line_error(exc)})") from None

    def gen() -> Iterator[can.Message]:
        n = 0
        try:
            for msg in reader:
                n += 1
                yield msg
        except Exception as exc:  # noqa: BLE001 - each of python-can's readers fails in its own way
            where = _candump_line(path, n) if _log_suffix(path) == ".log" else None
            what = "" if where is None else (f" at line {where[0]:,}, {where[1]!r}, not a candump -L frame "
                                             "'(time) channel id#data'")
            raise DataError(f"{path}: unreadable after {n:,} frames{what} ({one_line_error(exc)})") from None
        finally:
            stop = getattr(reader, "stop", None)
            if stop is not None:
                stop()
        if n == 0:
            raise DataError(f"{path}: no CAN frame in the log")

    return gen()


def _candump_line(path: Path, frames: int, shown: int = 60) -> tuple[int, str] | None:
    """(line number, text cut to ``shown`` characters) of a candump log's line after its first ``frames``
    frames: the one its reader failed on (one frame a non-blank line, as ``can.CanutilsLogReader`` reads)."""
    import gzip

    opener = gzip.open if path.suffix.lower() == ".gz" else open
    seen = 0
    try:
        with opener(path, "rt", encoding="utf-8", errors="replace") as fh:
            for number, line in enumerate(fh, start=1):
                if line.strip():
                    if seen == frames:
                        text = line.strip()
                        return number, text if len(text) <= shown else text[:shown] + "..."
                    seen += 1
    except (OSError, EOFError):
        return None
    return None


def _tail_lines(path: Path, nbytes: int = 8192) -> list[str]:
    with open(path, "rb") as fh:
        fh.seek(0, 2)
        size = fh.tell()
        fh.seek(max(0, size - nbytes))
        return fh.read().decode("utf-8", "replace").splitlines()


def _head_lines(path: Path, nbytes: int = 8192) -> list[str]:
    with open(path, "rb") as fh:
        return fh.read(nbytes).decode("utf-8", "replace").splitlines()


def log_span(path: str | Path) -> tuple[float, float] | None:
    """``(first, last)`` message time of a log without reading it all, as ``read_log`` reports
    them (an ASC file's times are relative to its start); ``None`` when unknown (``.gz``)."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".log":
            def ts(line: str) -> float | None:
                line = line.strip()
                if line.startswith("(") and ")" in line:
                    try:
                        return float(line[1 : line.index(")")])
                    except ValueError:
                        return None
                return None

            first = next((t for t in map(ts, _head_lines(path)) if t is not None), None)
            last = next((t for t in map(ts, reversed(_tail_lines(path))) if t is not None), None)
        elif suffix == ".asc":
            def ts(line: str) -> float | None:
                parts = line.split()
                if len(parts) < 3 or not parts[1][:1].isdigit():  # "<time> <channel> <id> ..."
                    return None
                try:
                    return float(parts[0])
                except ValueError:
                    return None

            first = next((t for t in map(ts, _head_lines(path, 65536)) if t is not None), None)
            last = next((t for t in map(ts, reversed(_tail_lines(path))) if t is not None), None)
        elif suffix == ".blf":
            from can.io.blf import BLFReader

            reader = BLFReader(str(path))
            try:
                first, last = float(reader.start_timestamp), float(reader.stop_timestamp)
            finally:
                reader.stop()
        else:
            return None
    except (OSError, ValueError, can.CanError, Exception):  # noqa: BLE001 - best effort (progress only)
        return None
    if first is None or last is None or not (math.isfinite(first) and math.isfinite(last)) or last <= first:
        return None
    return first, last


# ------------------------------------------------------------------- buses
def bus_config_from_args(args: Any) -> tuple[str, str | int | None, dict[str, Any]]:
    """``(interface, channel, other bus options)`` from python-can's command-line options
    (``can.cli.add_bus_arguments``), completed by python-can's configuration resolution
    (``$CAN_INTERFACE``, ``$CAN_CHANNEL``, ``$CAN_BITRATE``, ``~/.canrc``, ``can.ini``).
    Raises :class:`~bms_estimator.errors.UsageError` when no interface is given anywhere."""
    given: dict[str, Any] = {}
    for key in ("interface", "channel", "bitrate", "fd", "data_bitrate", "timing"):
        value = getattr(args, key, None)
        if value is not None and value is not False:
            given[key] = value
    given.update(getattr(args, "bus_kwargs", None) or {})
    try:
        cfg = dict(can.util.load_config(config=given))
    except can.CanInterfaceNotImplementedError as exc:
        if "interface" not in given:
            raise UsageError("no CAN interface: give -i/--interface, or set CAN_INTERFACE or ~/.canrc") from None
        raise UsageError(f"CAN interface: {exc}") from None
    interface = cfg.pop("interface", None)
    if not interface:
        raise UsageError("no CAN interface: give -i/--interface, or set CAN_INTERFACE or ~/.canrc")
    channel = cfg.pop("channel", None)
    cfg.pop("auto_reset", None)
    return str(interface), channel, {k: v for k, v in cfg.items() if v is not None and k in given}


def open_replay_bus(interface: str, channel: str | int | None = None, **kwargs: Any) -> can.BusABC:
    """The sending bus: ``virtual`` with ``preserve_timestamps=True`` (receivers see the log
    time); ``udp_multicast`` (default group when ``channel`` is None); ``socketcan`` and any
    other python-can interface as given. Raises :class:`~bms_estimator.errors.CanBusError`
    (one line) when it cannot be opened."""
    kw: dict[str, Any] = {"interface": interface, "receive_own_messages": False}
    if channel is not None:
        kw["channel"] = channel
    if interface == "virtual":
        kw["preserve_timestamps"] = True
    kw.update(kwargs)
    try:
        return can.Bus(**kw)
    except (can.CanError, OSError, ValueError, ImportError, TypeError) as exc:
        where = f"{interface}:{channel}" if channel is not None else interface
        raise CanBusError(f"cannot open CAN bus {where}: {one_line_error(exc)}") from None


from ..can.udp import UdpMulticastReceiver

#: the log-time receiver, kept under its old name
LogTimeUdpMulticastBus = UdpMulticastReceiver


def open_bus_log_time(cfg: Any) -> can.BusABC:
    """``bus_factory`` for :class:`bms_estimator.can.bus.ResilientBus` (``cfg``: its ``BusConfig``)
    that receives with the log's timestamps where the interface can carry them: ``udp_multicast``
    opens :class:`~bms_estimator.can.udp.UdpMulticastReceiver` with ``log_time=True``; everything else is ``bms_estimator.can.bus.open_bus``
    (``virtual`` already delivers the sender's timestamps when the sender preserves them)."""
    from ..can.bus import open_bus

    return open_bus(cfg, log_time=True)


# ------------------------------------------------------------------- replay
@dataclass
class ReplayStats:
    sent: int = 0
    send_errors: int = 0  # frames dropped after retries (bus full/down)
    first_log_s: float = math.nan
    last_log_s: float = math.nan
    wall_s: float = 0.0
    speed: float = 1.0
    stopped: bool = False  # ended by the stop event

    @property
    def log_duration_s(self) -> float:
        d = self.last_log_s - self.first_log_s
        return d if math.isfinite(d) else 0.0

    @property
    def effective_speed(self) -> float:
        """Log seconds per wall second (``inf`` for an instantaneous replay)."""
        if self.wall_s <= 0:
            return math.inf
        return self.log_duration_s / self.wall_s


#: the longest single sleep of a paced replay (time.sleep and Event.wait refuse ~292 years and more)
_MAX_WAIT_S = 86400.0

#: ``progress(sent, log_elapsed_s)``, called about every 0.1 s of wall time and at the end
ProgressCallback = Callable[[int, float], None]


def replay_messages(
    messages: Iterable[can.Message],
    bus: can.BusABC,
    speed: float | str = 1.0,
    progress: ProgressCallback | None = None,
    *,
    stop: threading.Event | None = None,
    send_timeout: float | None = None,
    send_retries: int = 50,
    retry_sleep_s: float = 0.002,
    clock: Callable[[], float] = time.perf_counter,
) -> ReplayStats:
    """Send ``messages`` on ``bus`` paced by their timestamps (module docstring); blocking.

    Usable in-process (e.g. from a thread next to an asyncio service: ``await
    asyncio.to_thread(replay_messages, msgs, bus, 50)``). The message objects are sent as
    they are (their ``channel`` is set to None). ``send_timeout`` is passed to
    ``bus.send`` (None = block, which gives flow control on a bounded virtual queue); a
    ``can.CanError`` is retried ``send_retries`` times ``retry_sleep_s`` apart, then the
    frame is counted in ``send_errors``. ``stop`` ends the replay early.
    """
    rate = parse_speed(speed)
    paced = math.isfinite(rate)
    stats = ReplayStats(speed=rate)
    send = bus.send
    next_report = 0.0
    t0_log = t0_wall = None
    start = clock()
    last_t = math.nan
    n = 0
    for msg in messages:
        t = msg.timestamp
        if t0_log is None:
            t0_log, t0_wall = t, clock()
            stats.first_log_s = t
            next_report = t0_wall + 0.1
        if paced:
            due = t0_wall + (t - t0_log) / rate
            # in slices: one wait beyond what the clock can sleep (a tiny speed, a clock jump) raised OverflowError
            while (delay := due - clock()) > 0:
                if stop is not None:
                    if stop.wait(min(delay, _MAX_WAIT_S)):
                        stats.stopped = True
                        break
                else:
                    time.sleep(min(delay, _MAX_WAIT_S))
            if stats.stopped:
                break
        if msg.channel is not None:
            msg.channel = None
        try:
            send(msg, send_timeout)
        except can.CanError:
            if not _retry(send, msg, send_timeout, send_retries, retry_sleep_s):
                stats.send_errors += 1
        n += 1
        last_t = t
        if not n & 0xFF:
            if stop is not None and stop.is_set():
                stats.stopped = True
                break
            if progress is not None:
                now = clock()
                if now >= next_report:
                    next_report = now + 0.1
                    progress(n, t - t0_log)
    stats.sent = n - stats.send_errors
    stats.last_log_s = last_t if n else math.nan
    stats.wall_s = clock() - start
    if progress is not None:
        progress(n, (last_t - t0_log) if n and t0_log is not None else 0.0)
    return stats


def _retry(send: Callable, msg: can.Message, timeout: float | None, retries: int, pause: float) -> bool:
    for _ in range(max(0, retries)):
        time.sleep(pause)
        try:
            send(msg, timeout)
            return True
        except can.CanError:
            continue
    return False
