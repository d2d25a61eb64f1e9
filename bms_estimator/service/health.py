"""Liveness and metrics over a small loopback HTTP server on the service's event loop.

* ``GET /healthz`` -> ``200 ok`` while the estimator loop's :class:`Heartbeat`
  is fresh (last beat within ``stale_after_periods`` sample periods), ``503``
  when stale and before the first beat; the body adds the service's status
  (e.g. the CAN bus state).
* ``GET /metrics`` -> the Prometheus exposition of the service's registry
  (:class:`~bms_estimator.service.metrics.ServiceMetrics`, prometheus_client's
  ``generate_latest``).
* anything else -> ``404`` (``405`` for a non-GET/HEAD on a known path,
  ``400`` for a malformed request line). Garbage, oversized or slow requests
  are answered or dropped without affecting the server.

Usage::

    hb = Heartbeat(cfg.estimator.sample_period_s, cfg.health.stale_after_periods)
    metrics = ServiceMetrics()
    server = HealthServer.from_config(cfg.health, hb, metrics, status=lambda: "CAN can0: open")
    tg.create_task(server.run())          # until cancelled
    ...; hb.beat()                        # every estimator tick
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import structlog
from prometheus_client.exposition import choose_encoder

if TYPE_CHECKING:
    from .config import HealthConfig
    from .metrics import ServiceMetrics

__all__ = ["HealthServer", "Heartbeat"]

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


_REASONS = {200: "OK", 400: "Bad Request", 404: "Not Found", 405: "Method Not Allowed", 503: "Service Unavailable"}
_TEXT = "text/plain; charset=utf-8"


class HealthServer:
    """asyncio HTTP/1.x server for ``/healthz`` and ``/metrics``."""

    MAX_LINE = 8192
    MAX_HEADERS = 100
    MAX_CONNECTIONS = 32

    def __init__(
        self,
        heartbeat: Heartbeat,
        metrics: ServiceMetrics | None,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        request_timeout_s: float = 5.0,
        status: Callable[[], str] | None = None,
    ) -> None:
        self.heartbeat = heartbeat
        self.metrics = metrics
        self.status = status
        self.host = host
        self._port = port
        self.request_timeout_s = request_timeout_s
        self._server: asyncio.base_events.Server | None = None
        self._active = 0

    @classmethod
    def from_config(cls, cfg: HealthConfig, heartbeat: Heartbeat, metrics: ServiceMetrics | None,
                    status: Callable[[], str] | None = None) -> HealthServer:
        return cls(heartbeat, metrics, cfg.host, cfg.port, status=status)

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
    def _route(self, method: str, target: str, headers: dict[str, str] | None = None) -> tuple[int, str, bytes]:
        path = target.split("?", 1)[0].split("#", 1)[0]
        if path not in ("/healthz", "/metrics") or (path == "/metrics" and self.metrics is None):
            return 404, _TEXT, b"not found\n"
        if method not in ("GET", "HEAD"):
            return 405, _TEXT, b"method not allowed\n"
        if path == "/metrics":
            assert self.metrics is not None
            # the library's content negotiation: Prometheus text, or OpenMetrics when asked for
            encoder, ctype = choose_encoder((headers or {}).get("accept", ""))
            return 200, ctype, encoder(self.metrics.registry)
        age = self.heartbeat.age_s()
        if age is None:
            status, text = 503, "starting: no estimator tick yet"
        elif not self.heartbeat.is_fresh():
            status, text = 503, f"stale: last estimator tick {age:.1f} s ago (limit {self.heartbeat.max_age_s:.1f} s)"
        else:
            status, text = 200, "ok"
        if self.status is not None:
            try:
                text += "\n" + self.status()
            except Exception:  # noqa: BLE001 - the answer must not depend on it
                log.exception("health status failed")
        return status, _TEXT, (text + "\n").encode("utf-8")

    async def _read_request(self, reader: asyncio.StreamReader) -> tuple[str, str, dict[str, str]] | None:
        line = await reader.readline()
        if not line:
            return None
        parts = line.decode("latin-1").split()
        if len(parts) != 3 or not parts[2].startswith("HTTP/") or not parts[1].startswith("/"):
            raise _BadRequest
        headers: dict[str, str] = {}
        for _ in range(self.MAX_HEADERS):
            header = await reader.readline()
            if header in (b"\r\n", b"\n", b""):
                return parts[0], parts[1], headers
            name, sep, value = header.decode("latin-1").partition(":")
            if sep:
                headers[name.strip().lower()] = value.strip()
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
                status, ctype, body = 400, _TEXT, b"bad request\n"
            else:
                if req is None:
                    return
                method = req[0]
                status, ctype, body = self._route(*req)
            payload = body
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
