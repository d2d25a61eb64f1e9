"""Liveness and metrics over a tiny loopback HTTP server (no dependency).

* ``GET /healthz`` -> ``200 ok`` while the estimator loop's :class:`Heartbeat`
  is fresh (last beat within ``stale_after_periods`` sample periods), ``503``
  when stale and before the first beat.
* ``GET /metrics`` -> Prometheus text exposition format rendered from a
  :class:`Metrics` registry that the rest of the service updates.
* anything else -> ``404`` (``405`` for a non-GET/HEAD on a known path,
  ``400`` for a malformed request line). Garbage, oversized or slow requests
  are answered or dropped without affecting the server.

Usage::

    hb = Heartbeat(cfg.estimator.sample_period_s, cfg.health.stale_after_periods)
    metrics = Metrics()
    server = HealthServer.from_config(cfg.health, hb, metrics)
    tg.create_task(server.run())          # until cancelled
    ...; hb.beat()                        # every estimator tick
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

import structlog

if TYPE_CHECKING:
    from .config import HealthConfig

__all__ = ["HealthServer", "Heartbeat", "Metrics"]

log = structlog.get_logger("bms.health")


class Heartbeat:
    """Last-tick timestamp of the estimator loop (monotonic clock)."""

    def __init__(
        self,
        period_s: float,
        stale_after_periods: float = 3.0,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not period_s > 0 or not stale_after_periods > 0:
            raise ValueError("period_s and stale_after_periods must be > 0")
        self.period_s = float(period_s)
        self.stale_after_periods = float(stale_after_periods)
        self._clock = clock
        self.last_beat: float | None = None
        self.beats = 0

    @property
    def max_age_s(self) -> float:
        return self.period_s * self.stale_after_periods

    def beat(self) -> None:
        self.last_beat = self._clock()
        self.beats += 1

    def age_s(self) -> float | None:
        """Seconds since the last beat, None before the first one."""
        if self.last_beat is None:
            return None
        return max(0.0, self._clock() - self.last_beat)

    def is_fresh(self) -> bool:
        age = self.age_s()
        return age is not None and age <= self.max_age_s


def _counter(help_: str) -> Any:
    return field(default=0, metadata={"kind": "counter", "help": help_})


def _gauge(help_: str, default: float = 0) -> Any:
    return field(default=default, metadata={"kind": "gauge", "help": help_})


@dataclass
class Metrics:
    """Counters and gauges of the service, rendered as Prometheus text.

    Update with plain attribute access (``metrics.samples += 1``) from the
    event loop, or with :meth:`inc` / :meth:`set` (thread-safe) from other
    threads. Counters get a ``_total`` suffix and every name a ``bms_``
    prefix in the exposition.
    """

    frames_decoded: int = _counter("CAN frames decoded")
    decode_errors: int = _counter("CAN frames that failed to decode")
    samples: int = _counter("estimator samples processed")
    estimator_rejections: int = _counter("samples or updates rejected by the estimator")
    mqtt_published: int = _counter("MQTT messages published")
    mqtt_dropped: int = _counter("MQTT states dropped (superseded or buffer overflow)")
    mqtt_connects: int = _counter("successful MQTT connections")
    mqtt_connect_failures: int = _counter("failed MQTT connection attempts")
    state_saves: int = _counter("estimator state files written")
    state_save_errors: int = _counter("estimator state saves that failed")
    loop_lag_seconds: float = _gauge("lateness of the last estimator tick against its schedule")
    cells_stale: int = _gauge("cells whose inputs are stale")
    mqtt_connected: int = _gauge("1 while connected to the MQTT broker")

    def __post_init__(self) -> None:
        self._lock = threading.Lock()

    def inc(self, name: str, n: int | float = 1) -> None:
        with self._lock:
            setattr(self, name, getattr(self, name) + n)

    def set(self, name: str, value: int | float) -> None:
        with self._lock:
            if not hasattr(self, name):
                raise AttributeError(name)
            setattr(self, name, value)

    def snapshot(self) -> dict[str, int | float]:
        with self._lock:
            return {f.name: getattr(self, f.name) for f in fields(self)}

    def render(self, heartbeat: Heartbeat | None = None) -> str:
        """Prometheus text exposition format (version 0.0.4)."""
        values = self.snapshot()
        out: list[str] = []
        for f in fields(self):
            kind = f.metadata.get("kind", "gauge")
            name = f"bms_{f.name}" + ("_total" if kind == "counter" else "")
            out.append(f"# HELP {name} {f.metadata.get('help', f.name)}")
            out.append(f"# TYPE {name} {kind}")
            out.append(f"{name} {_fmt(values[f.name])}")
        if heartbeat is not None:
            age = heartbeat.age_s()
            out.append("# HELP bms_heartbeat_age_seconds seconds since the last estimator tick (NaN before the first)")
            out.append("# TYPE bms_heartbeat_age_seconds gauge")
            out.append(f"bms_heartbeat_age_seconds {_fmt(math.nan if age is None else age)}")
            out.append("# HELP bms_healthy 1 while the estimator heartbeat is fresh")
            out.append("# TYPE bms_healthy gauge")
            out.append(f"bms_healthy {1 if heartbeat.is_fresh() else 0}")
        return "\n".join(out) + "\n"


def _fmt(value: Any) -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return "NaN"
    if math.isnan(v):
        return "NaN"
    if math.isinf(v):
        return "+Inf" if v > 0 else "-Inf"
    if v.is_integer() and abs(v) < 2**53:
        return str(int(v))
    return repr(v)


_REASONS = {200: "OK", 400: "Bad Request", 404: "Not Found", 405: "Method Not Allowed", 503: "Service Unavailable"}
_TEXT = "text/plain; charset=utf-8"
_PROM = "text/plain; version=0.0.4; charset=utf-8"


class HealthServer:
    """asyncio HTTP/1.x server for ``/healthz`` and ``/metrics``."""

    MAX_LINE = 8192
    MAX_HEADERS = 100
    MAX_CONNECTIONS = 32

    def __init__(
        self,
        heartbeat: Heartbeat,
        metrics: Metrics,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        request_timeout_s: float = 5.0,
    ) -> None:
        self.heartbeat = heartbeat
        self.metrics = metrics
        self.host = host
        self._port = port
        self.request_timeout_s = request_timeout_s
        self._server: asyncio.base_events.Server | None = None
        self._active = 0

    @classmethod
    def from_config(cls, cfg: HealthConfig, heartbeat: Heartbeat, metrics: Metrics) -> HealthServer:
        return cls(heartbeat, metrics, cfg.host, cfg.port)

    @property
    def port(self) -> int:
        """The bound port (the real one when configured as 0)."""
        if self._server is not None and self._server.sockets:
            return int(self._server.sockets[0].getsockname()[1])
        return self._port

    async def start(self) -> None:
        if self._server is not None:
            return
        self._server = await asyncio.start_server(
            self._handle, self.host, self._port, limit=self.MAX_LINE, reuse_address=True
        )
        log.info("health server listening", host=self.host, port=self.port)

    async def close(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), timeout=2.0)

    async def run(self) -> None:
        """Serve until cancelled (then close the listening socket)."""
        await self.start()
        try:
            await asyncio.Event().wait()
        finally:
            await self.close()

    async def __aenter__(self) -> HealthServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ------------------------------------------------------------------ request
    def _route(self, method: str, target: str) -> tuple[int, str, str]:
        path = target.split("?", 1)[0].split("#", 1)[0]
        if path not in ("/healthz", "/metrics"):
            return 404, _TEXT, "not found\n"
        if method not in ("GET", "HEAD"):
            return 405, _TEXT, "method not allowed\n"
        if path == "/metrics":
            return 200, _PROM, self.metrics.render(self.heartbeat)
        age = self.heartbeat.age_s()
        if age is None:
            return 503, _TEXT, "starting: no estimator tick yet\n"
        if not self.heartbeat.is_fresh():
            return 503, _TEXT, f"stale: last estimator tick {age:.1f} s ago (limit {self.heartbeat.max_age_s:.1f} s)\n"
        return 200, _TEXT, "ok\n"

    async def _read_request(self, reader: asyncio.StreamReader) -> tuple[str, str] | None:
        line = await reader.readline()
        if not line:
            return None
        parts = line.decode("latin-1").split()
        if len(parts) != 3 or not parts[2].startswith("HTTP/") or not parts[1].startswith("/"):
            raise _BadRequest
        for _ in range(self.MAX_HEADERS):
            header = await reader.readline()
            if header in (b"\r\n", b"\n", b""):
                return parts[0], parts[1]
        raise _BadRequest

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._active += 1
        try:
            if self._active > self.MAX_CONNECTIONS:
                return
            method = "GET"
            try:
                req = await asyncio.wait_for(self._read_request(reader), self.request_timeout_s)
            except (_BadRequest, ValueError, asyncio.LimitOverrunError, UnicodeError):
                status, ctype, body = 400, _TEXT, "bad request\n"
            else:
                if req is None:
                    return
                method = req[0]
                status, ctype, body = self._route(*req)
            payload = body.encode("utf-8")
            head = (
                f"HTTP/1.1 {status} {_REASONS.get(status, 'Error')}\r\n"
                f"Content-Type: {ctype}\r\n"
                f"Content-Length: {len(payload)}\r\n"
                "Cache-Control: no-store\r\n"
                "Connection: close\r\n"
                + ("Allow: GET, HEAD\r\n" if status == 405 else "")
                + "\r\n"
            ).encode("ascii")
            writer.write(head if method == "HEAD" else head + payload)
            await asyncio.wait_for(writer.drain(), self.request_timeout_s)
        except (asyncio.TimeoutError, ConnectionError, OSError):
            pass
        except Exception:  # never let one request take the server down
            log.exception("health request failed")
        finally:
            self._active -= 1
            writer.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.wait_closed(), 1.0)


class _BadRequest(Exception):
    pass
