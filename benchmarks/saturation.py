"""Input loss at a saturated bus: the real ``bms-estimator run`` at 200 cells and ~7,400 frames/s.

The service runs as its own process with CAN output and MQTT on (a Mosquitto it
can reach, when installed), reading ``udp_multicast`` in a network namespace
made for the run (the only cross-process CAN transport without SocketCAN). A
sender replays :func:`benchmarks.can_frames.synth_frames` in real time with
every cell voltage every 9 ms: 200 cells on the project DBC is about 7,560
frames/s, a saturated 1 Mbit/s bus. At the end ``/metrics`` says what the
service received and what it counted as lost (receive queue, malformed,
kernel socket buffer). Reported:

* ``loss_pct``: frames sent but not received, in % of sent;
* ``uncounted``: of those, how many no counter owns (the goal: 0).

Needs root (``ip netns``); returns None with the reason where it cannot run.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path

__all__ = ["SaturationResult", "bench_saturation", "bench_saturation_loss_pct"]

REPO = Path(__file__).resolve().parents[1]
GROUP = "239.74.163.2"


@dataclass
class SaturationResult:
    sent: int
    received: int
    counted_lost: dict[str, int]
    loss_pct: float
    uncounted: int
    frames_per_s: float
    seconds: float
    mqtt: bool
    samples: int
    tick_p99_ms: float | None  # upper bound of the histogram bucket holding the 99th percentile
    loop_lag_p99_ms: float | None
    receive_buffer_bytes: int | None  # None: the service's default

    def as_dict(self) -> dict:
        return asdict(self)


_INNER = textwrap.dedent(
    r"""
    import json, os, subprocess, sys, tempfile, time, urllib.request
    from pathlib import Path
    sys.path.insert(0, {repo!r})
    import can
    from prometheus_client.parser import text_string_to_metric_families
    from benchmarks.can_frames import synth_frames
    from bms_estimator.can.dbc import load_project_db
    from bms_estimator.mosquitto import Mosquitto, MosquittoError, free_port

    n_cells, seconds, port = {n_cells}, {seconds}, {port}
    rcvbuf = "" if {rcvbuf!r} is None else ", receive_buffer_bytes = {rcvbuf}"
    work = Path(tempfile.mkdtemp(prefix="bms-sat-"))
    broker = None
    try:
        broker = Mosquitto(work / "mqtt").start()
    except MosquittoError:
        broker = None
    health = free_port()
    cfg = work / "config.toml"
    cfg.write_text(f'''
    [pack]
    pack_id = "sat"
    n_cells = {{n_cells}}
    capacity_ah = 3.0
    [can]
    interface = "udp_multicast"
    channel = "{group}"
    [can.bus]
    options = {{{{ port = {{port}}{{rcvbuf}} }}}}
    [can.output]
    enabled = true
    [mqtt]
    enabled = {{"true" if broker else "false"}}
    host = "127.0.0.1"
    port = {{broker.port if broker else 1883}}
    [state]
    path = "{{work / 'state.npz'}}"
    [health]
    port = {{health}}
    [logging]
    level = "WARNING"
    '''.replace("\n    ", "\n"))
    svc = subprocess.Popen([sys.executable, "-m", "bms_estimator.cli", "run", "--config", str(cfg)],
                           stdout=subprocess.DEVNULL, stderr=open(work / "service.log", "w"))

    def scrape():
        with urllib.request.urlopen(f"http://127.0.0.1:{{health}}/metrics", timeout=5) as r:
            text = r.read().decode()
        out = {{}}
        for fam in text_string_to_metric_families(text):
            for s in fam.samples:
                out[(s.name, tuple(sorted(s.labels.items())))] = s.value
        return out

    try:
        for _ in range(200):
            try:
                m = scrape()
                if m.get(("bms_can_bus_up", ())) == 1:
                    break
            except OSError:
                pass
            time.sleep(0.05)
        frames = synth_frames(load_project_db(), "default", n_cells, seconds, voltage_period_s=0.009)
        bus = can.Bus(interface="udp_multicast", channel="{group}", port=port)
        t0 = time.perf_counter()
        f0 = frames[0].timestamp
        sent = 0
        for msg in frames:
            due = t0 + (msg.timestamp - f0)
            now = time.perf_counter()
            if due > now:
                time.sleep(due - now)
            bus.send(msg)
            sent += 1
        wall = time.perf_counter() - t0
        bus.shutdown()

        def accounted(m):
            drops = sum(v for k, v in m.items() if k[0] == "bms_can_rx_dropped_total")
            return m.get(("bms_can_frames_received_total", ()), 0) + drops

        # until the service has taken everything it will take (a bound, not a measurement)
        m, last, still = scrape(), -1, 0
        for _ in range(300):
            n = accounted(m)
            if n >= sent:
                break
            still = still + 1 if n == last else 0
            if still >= 10:
                break
            last = n
            time.sleep(0.1)
            m = scrape()
    finally:
        svc.terminate()
        try:
            svc.wait(10)
        except subprocess.TimeoutExpired:
            svc.kill()
        if broker is not None:
            broker.stop()
    lost = {{k[1][0][1]: int(v) for k, v in m.items() if k[0] == "bms_can_rx_dropped_total"}}

    def p99(name):
        hist = sorted((float(dict(k[1])["le"]), v) for k, v in m.items() if k[0] == name)
        total = hist[-1][1] if hist else 0
        return next((le for le, c in hist if total and c >= 0.99 * total), None)

    print(json.dumps({{"sent": sent, "received": int(m.get(("bms_can_frames_received_total", ()), 0)),
                      "lost": lost, "wall": wall, "mqtt": broker is not None,
                      "samples": int(m.get(("bms_samples_total", ()), 0)),
                      "tick_p99_s": p99("bms_tick_seconds_bucket"),
                      "lag_p99_s": p99("bms_loop_lag_seconds_bucket")}}))
    """
)


def _all_cores() -> None:
    """The sender and the service get the whole machine (``bench`` pins itself to one core)."""
    try:
        os.sched_setaffinity(0, range(os.cpu_count() or 1))
    except (AttributeError, OSError):
        pass


def bench_saturation(n_cells: int = 200, seconds: float = 20.0, *,
                     receive_buffer_bytes: int | None = None) -> SaturationResult | str:
    """Run it (see the module docstring); the result, or the reason it could not run.

    ``receive_buffer_bytes`` sets the service's ``SO_RCVBUF`` (``can.bus.options``), e.g. small,
    to see what a receiver that falls behind loses and counts."""
    ip = shutil.which("ip")
    if ip is None:
        return "no 'ip' command"
    ns = f"bmssat-{os.getpid()}-{uuid.uuid4().hex[:4]}"
    r = subprocess.run([ip, "netns", "add", ns], capture_output=True, text=True)
    if r.returncode != 0:
        return f"cannot create a network namespace: {r.stderr.strip() or r.returncode}"
    try:
        for cmd in (["link", "set", "lo", "up"], ["route", "add", "224.0.0.0/4", "dev", "lo"]):
            r = subprocess.run([ip, "-n", ns, *cmd], capture_output=True, text=True)
            if r.returncode != 0:
                return f"netns: 'ip {' '.join(cmd)}' failed: {r.stderr.strip()}"
        script = _INNER.format(repo=str(REPO), n_cells=n_cells, seconds=seconds, port=43200, group=GROUP,
                               rcvbuf=receive_buffer_bytes)
        env = dict(os.environ, PYTHONPATH=str(REPO))
        r = subprocess.run([ip, "netns", "exec", ns, sys.executable, "-c", script], capture_output=True,
                           text=True, env=env, timeout=seconds + 120, preexec_fn=_all_cores)
        if r.returncode != 0:
            return f"saturation run failed: {r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode}"
        d = json.loads(r.stdout.strip().splitlines()[-1])
    finally:
        subprocess.run([ip, "netns", "del", ns], capture_output=True)
    sent, received = d["sent"], d["received"]
    lost = d["lost"]
    missing = sent - received
    return SaturationResult(
        sent=sent, received=received, counted_lost=lost, loss_pct=100.0 * missing / sent if sent else 0.0,
        uncounted=max(0, missing - sum(lost.values())), frames_per_s=sent / d["wall"], seconds=d["wall"],
        mqtt=d["mqtt"], samples=d["samples"],
        tick_p99_ms=None if d["tick_p99_s"] is None else 1000.0 * d["tick_p99_s"],
        loop_lag_p99_ms=None if d["lag_p99_s"] is None else 1000.0 * d["lag_p99_s"],
        receive_buffer_bytes=receive_buffer_bytes,
    )


def bench_saturation_loss_pct(n_cells: int = 200, seconds: float = 20.0) -> float | None:
    """``loss_pct`` of :func:`bench_saturation`, None where it cannot run."""
    res = bench_saturation(n_cells, seconds)
    return res.loss_pct if isinstance(res, SaturationResult) else None


if __name__ == "__main__":
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 20.0
    rcvbuf = int(sys.argv[2]) if len(sys.argv) > 2 else None
    t = time.perf_counter()
    res = bench_saturation(seconds=seconds, receive_buffer_bytes=rcvbuf)
    print(res if isinstance(res, str) else json.dumps(res.as_dict(), indent=1),
          f"({time.perf_counter() - t:.0f} s)", file=sys.stdout)
