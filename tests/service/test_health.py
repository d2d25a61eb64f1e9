"""/healthz and /metrics over real HTTP on a free loopback port."""

from __future__ import annotations

import asyncio
import platform
import sys
import re

import pytest
from service_helpers import run_async

from bms_estimator.service.config import HealthConfig
from bms_estimator.service.health import HealthServer, Heartbeat
from bms_estimator.service.metrics import ServiceMetrics, package_version


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


async def http(port: int, raw: bytes, timeout: float = 5.0) -> tuple[int, dict[str, str], bytes]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(raw)
    await writer.drain()
    data = await asyncio.wait_for(reader.read(), timeout)
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1])
    headers = {k.lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:] if ":" in line)}
    return status, headers, body


def get(port: int, path: str, headers: dict[str, str] | None = None):
    extra = "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
    return http(port, f"GET {path} HTTP/1.1\r\nHost: x\r\n{extra}\r\n".encode())


def test_healthz_follows_heartbeat():
    clock = FakeClock()
    hb = Heartbeat(period_s=1.0, stale_after_periods=3.0, clock=clock)

    async def main():
        async with HealthServer(hb, ServiceMetrics(), "127.0.0.1", 0) as srv:
            assert srv.port > 0
            status, _, body = await get(srv.port, "/healthz")
            assert status == 503 and b"no estimator tick" in body  # before the first tick

            hb.beat()
            clock.t += 2.9
            status, headers, body = await get(srv.port, "/healthz")
            assert (status, body) == (200, b"ok\n")
            assert headers["content-length"] == "3"  # and http() read to EOF: the server closed

            clock.t += 0.2  # 3.1 s since the last tick > 3 periods
            status, _, body = await get(srv.port, "/healthz?verbose=1")
            assert status == 503 and b"stale" in body

            hb.beat()
            status, _, _ = await get(srv.port, "/healthz")
            assert status == 200

    run_async(main())


def test_healthz_with_real_clock_and_stalled_loop():
    hb = Heartbeat(period_s=0.1, stale_after_periods=3.0)  # stale after 0.3 s without a tick

    async def main():
        async with HealthServer(hb, ServiceMetrics(), "127.0.0.1", 0) as srv:
            async def loop(ticks: int):
                for _ in range(ticks):
                    hb.beat()
                    await asyncio.sleep(0.1)

            ticking = asyncio.create_task(loop(6))
            await asyncio.sleep(0.25)
            assert (await get(srv.port, "/healthz"))[0] == 200
            await ticking  # the loop "stalls": no more beats
            await asyncio.sleep(0.5)
            assert (await get(srv.port, "/healthz"))[0] == 503

    run_async(main())


SAMPLE_LINE = re.compile(r"^[a-zA-Z_:][a-zA-Z0-9_:]* (NaN|[+-]Inf|-?[0-9]+(\.[0-9]+)?([eE][+-]?[0-9]+)?)$")


def parse_metrics(text: str) -> dict[str, float]:
    values: dict[str, float] = {}
    types: dict[str, str] = {}
    for line in text.splitlines():
        if line.startswith("# TYPE "):
            _, _, name, kind = line.split()
            types[name] = kind
            continue
        if line.startswith("#") or not line:
            continue
        assert SAMPLE_LINE.match(line), f"not 'name value': {line!r}"
        name, value = line.split(" ")
        assert name in types, f"{name} has no # TYPE"
        values[name] = float(value)
    return values


def test_metrics_exposition():
    """/metrics is prometheus_client's exposition of the service's registry: counters, the
    state as an Enum, histograms, process and build info; parsed by the library's parser."""
    from prometheus_client.parser import text_string_to_metric_families

    from bms_estimator.service.schema import EstimatorState

    hb = Heartbeat(1.0)
    metrics = ServiceMetrics()
    metrics.mqtt_published.inc(42)
    metrics.mqtt_dropped.inc(7)
    for dt in (0.0002, 0.0004, 0.03):
        metrics.observe_tick(dt)
    metrics.loop_lag_seconds.observe(0.0125)
    metrics.set_state(EstimatorState.DEGRADED)

    async def main():
        async with HealthServer(hb, metrics, "127.0.0.1", 0) as srv:
            status, headers, body = await get(srv.port, "/metrics")
            assert status == 200
            assert headers["content-type"].startswith("text/plain; version=")
            families = {f.name: f for f in text_string_to_metric_families(body.decode())}
            samples = {(s.name, tuple(sorted(s.labels.items()))): s.value
                       for f in families.values() for s in f.samples}
            assert families["bms_mqtt_published"].type == "counter"
            assert samples[("bms_mqtt_published_total", ())] == 42
            assert samples[("bms_mqtt_dropped_total", ())] == 7
            assert families["bms_tick_seconds"].type == "histogram"
            assert samples[("bms_tick_seconds_count", ())] == 3
            assert samples[("bms_tick_seconds_bucket", (("le", "0.0005"),))] == 2
            assert samples[("bms_loop_lag_seconds_count", ())] == 1
            states = {dict(k)["bms_estimator_state"]: v for (n, k), v in samples.items() if n == "bms_estimator_state"}
            assert states == {"init": 0, "running": 0, "degraded": 1, "no_input": 0}
            assert samples[("bms_build_info", (("python", platform.python_version()),
                                               ("version", package_version())))] == 1
            assert ("process_cpu_seconds_total", ()) in samples or sys.platform != "linux"
            # the library's content negotiation: OpenMetrics when the scraper asks for it
            status, headers, body = await get(srv.port, "/metrics",
                                              headers={"Accept": "application/openmetrics-text; version=1.0.0"})
            assert status == 200 and headers["content-type"].startswith("application/openmetrics-text")
            assert body.rstrip().endswith(b"# EOF") and b"bms_mqtt_published_total 42.0" in body
            # liveness stays plain text
            status, _, body = await get(srv.port, "/healthz")
            assert status == 503 and body.startswith(b"starting")

    run_async(main())


def test_other_paths_methods_and_garbage():
    hb = Heartbeat(1.0)
    hb.beat()

    async def main():
        async with HealthServer(hb, ServiceMetrics(), "127.0.0.1", 0, request_timeout_s=0.5) as srv:
            port = srv.port
            assert (await get(port, "/"))[0] == 404
            assert (await get(port, "/healthz/../etc/passwd"))[0] == 404
            assert (await http(port, b"POST /healthz HTTP/1.1\r\nContent-Length: 0\r\n\r\n"))[0] == 405
            status, headers, body = await http(port, b"HEAD /healthz HTTP/1.1\r\n\r\n")
            assert status == 200 and body == b"" and headers["content-length"] == "3"
            assert (await http(port, b"\x00\xff /healthz HTTP/1.1\r\n\r\n"))[0] == 405  # a junk method
            # no version reads as HTTP/0.9: the stdlib answers 400 the 0.9 way, without a status line
            for junk in (b"\x00\xff garbage\r\n\r\n", b"GET\r\n\r\n"):
                r, w = await asyncio.open_connection("127.0.0.1", port)
                w.write(junk)
                assert b"400" in await asyncio.wait_for(r.read(), 3)
                w.close()
            assert (await http(port, b"GET /" + b"a" * 20000 + b" HTTP/1.1\r\n\r\n"))[0] == 404
            assert (await http(port, b"GET /" + b"a" * 70000 + b" HTTP/1.1\r\n\r\n"))[0] == 414
            assert (await http(port, b"GET /healthz HTTP/1.1\r\n" + b"X: y\r\n" * 200 + b"\r\n"))[0] == 431

            # A client that connects and says nothing is dropped after the timeout...
            r, w = await asyncio.open_connection("127.0.0.1", port)
            assert await asyncio.wait_for(r.read(), 3) == b""
            w.close()
            # ...one that closes at once does no harm.
            r, w = await asyncio.open_connection("127.0.0.1", port)
            w.close()
            # and the server still answers.
            assert (await get(port, "/healthz"))[0] == 200

    run_async(main())


def test_answers_while_the_event_loop_is_blocked():
    """The server has its own thread: a wedged estimator loop still gets scraped, and /healthz
    says 503 (stale) instead of timing out."""
    import json
    import time
    import urllib.error
    import urllib.request
    from concurrent.futures import ThreadPoolExecutor

    hb = Heartbeat(period_s=0.1, stale_after_periods=3.0)
    metrics = ServiceMetrics()
    metrics.mqtt_published.inc(3)

    def fetch(port: int, path: str) -> tuple[int, bytes]:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as r:
                return r.status, r.read()
        except urllib.error.HTTPError as e:
            return e.code, e.read()

    async def main():
        async with HealthServer(hb, metrics, "127.0.0.1", 0) as srv:
            hb.beat()
            with ThreadPoolExecutor(2) as pool:
                time.sleep(0.05)
                healthy = pool.submit(fetch, srv.port, "/healthz").result(timeout=5)
                time.sleep(0.5)  # the loop is blocked: no beat, no await
                stale = pool.submit(fetch, srv.port, "/healthz").result(timeout=5)
                scraped = pool.submit(fetch, srv.port, "/metrics").result(timeout=5)
            assert healthy == (200, b"ok\n"), json.dumps(str(healthy))
            assert stale[0] == 503 and stale[1].startswith(b"stale")
            assert scraped[0] == 200 and b"bms_mqtt_published_total 3.0" in scraped[1]

    run_async(main())


def test_idle_connections_do_not_lock_out_healthz():
    """40 idle local connections (issue 16: /healthz was refused from 32 on) and it still answers."""
    hb = Heartbeat(1.0)
    hb.beat()

    async def main():
        async with HealthServer(hb, ServiceMetrics(), "127.0.0.1", 0, request_timeout_s=3.0) as srv:
            idle = [await asyncio.open_connection("127.0.0.1", srv.port) for _ in range(40)]
            try:
                await asyncio.sleep(0.2)
                status, _, body = await get(srv.port, "/healthz")
                assert (status, body) == (200, b"ok\n")
            finally:
                for _, w in idle:
                    w.close()

    run_async(main())


def test_from_config_and_run_task_is_cancellable():
    cfg = HealthConfig(port=0)
    hb = Heartbeat(1.0)

    async def main():
        srv = HealthServer.from_config(cfg, hb, ServiceMetrics())
        task = asyncio.create_task(srv.run())
        for _ in range(100):
            if srv.port:
                break
            await asyncio.sleep(0.01)
        port = srv.port
        assert (await get(port, "/healthz"))[0] == 503
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        with pytest.raises(OSError):
            await asyncio.open_connection("127.0.0.1", port)

    run_async(main())


def test_heartbeat_validation():
    with pytest.raises(ValueError):
        Heartbeat(0)
    hb = Heartbeat(2.0, 3.0)
    assert hb.max_age_s == 6.0 and hb.age_s() is None and not hb.is_fresh()
