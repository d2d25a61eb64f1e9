"""Liveness and metrics over prometheus_client's WSGI server, on loopback by default.

* ``GET /healthz`` -> ``200 ok`` while the estimator loop's :class:`Heartbeat`
  is fresh (last beat within ``stale_after_periods`` sample periods), ``503``
  when stale and before the first beat; the body adds the service's status
  (e.g. the CAN bus state).
* ``GET /metrics`` -> the Prometheus exposition of the service's registry
  (:class:`~bms_estimator.service.metrics.ServiceMetrics`, prometheus_client's
  ``generate_latest``).
* anything else -> ``404`` (``405`` for a non-GET/HEAD on a known path;
  the standard library's HTTP parser answers a malformed request with ``400``,
  too many headers with ``431``, an oversized request line with ``414``). Slow
  or silent clients are dropped after ``request_timeout_s``; none affects the
  service, whose event loop the server does not share.

Usage::

    hb = Heartbeat(cfg.estimator.sample_period_s, cfg.health.stale_after_periods)
    metrics = ServiceMetrics()
    server = HealthServer.from_config(cfg.health, hb, metrics, status=lambda: "CAN can0: open")
    tg.create_task(server.run())          # until cancelled
    ...; hb.beat()                        # every estimator tick
"""

from __future__ import annotations

import asyncio
import socket
import sys
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from typing import TYPE_CHECKING
from wsgiref.simple_server import WSGIRequestHandler, make_server

import structlog
from prometheus_client import make_wsgi_app
from prometheus_client.exposition import ThreadingWSGIServer

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


_TEXT = "text/plain; charset=utf-8"


class _Handler(WSGIRequestHandler):
    """wsgiref's handler, bounded in time and quiet (its access log goes to debug)."""

    timeout = 5.0  # socket timeout: a client that says nothing is dropped (set per server)

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - the library's name
        log.debug("health request", client=self.client_address[0], message=format % args)


class HealthServer:
    """``/healthz`` and ``/metrics``, served the library's way in a thread beside the event loop.

    ``/metrics`` is :func:`prometheus_client.make_wsgi_app` on the service's registry
    (its content negotiation, gzip and ``name[]`` filters included); ``/healthz`` is a
    small WSGI app beside it; :class:`prometheus_client.exposition.ThreadingWSGIServer`
    serves both, as :func:`prometheus_client.start_http_server` does.  In its own
    thread the server answers while the event loop is busy or wedged, so a scraper
    still sees the metrics of a stalled loop, and ``/healthz`` says 503 instead of
    timing out.  Bounded: ``request_timeout_s`` per connection, ``MAX_CONNECTIONS``
    at once (more are closed unanswered).
    """

    MAX_CONNECTIONS = 256  # one thread each, for at most request_timeout_s: idle clients cannot lock a scraper out

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
        self._metrics_app = make_wsgi_app(metrics.registry) if metrics is not None else None
        self._httpd: ThreadingWSGIServer | None = None
        self._thread: threading.Thread | None = None

    @classmethod
    def from_config(cls, cfg: HealthConfig, heartbeat: Heartbeat, metrics: ServiceMetrics | None,
                    status: Callable[[], str] | None = None) -> HealthServer:
        return cls(heartbeat, metrics, cfg.host, cfg.port, status=status)

    @property
    def port(self) -> int:
        """The bound port (the real one when configured as 0)."""
        if self._httpd is not None:
            return int(self._httpd.server_address[1])
        return self._port

    def start_sync(self) -> None:
        """Bind and start serving in a daemon thread (OSError if the address is taken)."""
        if self._httpd is not None:
            return
        family = socket.getaddrinfo(self.host, self._port, type=socket.SOCK_STREAM)[0][0]
        limit = threading.BoundedSemaphore(self.MAX_CONNECTIONS)

        class Server(ThreadingWSGIServer):
            address_family = family
            request_queue_size = 128  # socketserver's 5 drops SYNs of a burst of clients: 1-3 s retries

            def handle_error(self, request, client_address):  # type: ignore[no-untyped-def]
                # a client that timed out or hung up: one debug line, not a traceback on stderr
                log.debug("health connection dropped", client=client_address[0], error=repr(sys.exc_info()[1]))

            def process_request(self, request, client_address):  # type: ignore[no-untyped-def]
                if not limit.acquire(blocking=False):
                    self.shutdown_request(request)  # too many at once: closed unanswered
                    return
                super().process_request(request, client_address)

            def process_request_thread(self, request, client_address):  # type: ignore[no-untyped-def]
                try:
                    super().process_request_thread(request, client_address)
                finally:
                    limit.release()

        handler = type("Handler", (_Handler,), {"timeout": self.request_timeout_s})
        httpd = make_server(self.host, self._port, self._app, Server, handler)
        self._httpd = httpd
        self._thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="bms-health", daemon=True)
        self._thread.start()
        log.info("health server listening", host=self.host, port=self.port)

    def close_sync(self) -> None:
        httpd, self._httpd = self._httpd, None
        if httpd is not None:
            httpd.shutdown()
            httpd.server_close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    async def start(self) -> None:
        self.start_sync()

    async def close(self) -> None:
        await asyncio.to_thread(self.close_sync)

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

    # ------------------------------------------------------------------ WSGI
    def _app(self, environ: dict, start_response: Callable) -> list[bytes]:
        path = environ.get("PATH_INFO", "")
        method = environ.get("REQUEST_METHOD", "GET")
        if path == "/metrics" and self._metrics_app is not None:
            if method not in ("GET", "HEAD"):
                return self._reply(start_response, 405, b"method not allowed\n", method)
            body = b"".join(self._metrics_app(environ, start_response))
            return [b""] if method == "HEAD" else [body]
        if path != "/healthz":
            return self._reply(start_response, 404, b"not found\n", method)
        if method not in ("GET", "HEAD"):
            return self._reply(start_response, 405, b"method not allowed\n", method)
        status, text = self.health()
        return self._reply(start_response, status, (text + "\n").encode("utf-8"), method)

    def health(self) -> tuple[int, str]:
        """``(HTTP status, text)`` of ``/healthz`` now."""
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
        return status, text

    @staticmethod
    def _reply(start_response: Callable, status: int, body: bytes, method: str) -> list[bytes]:
        headers = [("Content-Type", _TEXT), ("Content-Length", str(len(body))), ("Cache-Control", "no-store")]
        if status == 405:
            headers.append(("Allow", "GET, HEAD"))
        start_response(f"{status} {HTTPStatus(status).phrase}", headers)
        return [b""] if method == "HEAD" else [body]
