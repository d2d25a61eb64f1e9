"""SIGHUP: the running daemon re-reads its configuration (``systemctl reload``).

A real ``bms-estimator run`` process on a ``virtual`` bus: a SIGHUP with a configuration that
no longer validates keeps the service running on the one it has, and says why; a SIGHUP with a
valid one stops the service as SIGTERM does (state saved) and starts it again on the new
configuration, from that state; SIGTERM then ends it with exit code 0.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

from bms_estimator.service.state import load_state

REPO_ROOT = Path(__file__).resolve().parents[2]
PACK, N = "packR", 6


class LogReader:
    """The JSON log lines of a process's stderr, read by a thread as they come."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.events: list[dict] = []
        self.text: list[str] = []
        self.ended = False  # stderr closed: the process is gone
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(proc.stderr,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        for raw in stream:
            line = raw.decode(errors="replace")
            with self._cond:
                self.text.append(line)
                if line.startswith("{"):
                    self.events.append(json.loads(line))
                self._cond.notify_all()
        with self._cond:
            self.ended = True
            self._cond.notify_all()

    def wait_for(self, event: str, count: int = 1, timeout: float = 15.0) -> list[dict]:
        """Block until ``event`` was logged ``count`` times; those log records."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                got = [e for e in self.events if e.get("event") == event]
                if len(got) >= count:
                    return got
                left = deadline - time.monotonic()
                if left <= 0 or self.ended:
                    why = "the process ended" if self.ended else f"not within {timeout} s"
                    raise AssertionError(f"no {event!r} (x{count}): {why}; log:\n" + "".join(self.text[-10:]))
                self._cond.wait(left)


def write_config(path: Path, state: Path, *, n_cells: int | str = N, level: str = "INFO") -> None:
    path.write_text(
        f"[pack]\npack_id = '{PACK}'\nn_cells = {n_cells}\ncapacity_ah = 2.9\n"
        f"[can]\ninterface = 'virtual'\nchannel = 'bmsr-{uuid.uuid4().hex[:8]}'\n"
        "[mqtt]\nenabled = false\n"
        f"[state]\npath = '{state}'\n"
        "[health]\nenabled = false\n"
        f"[logging]\nformat = 'json'\nlevel = '{level}'\n"
    )


@pytest.fixture
def daemon(tmp_path):
    state, cfg = tmp_path / "state.npz", tmp_path / "config.toml"
    write_config(cfg, state)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("BMS_", "NOTIFY_SOCKET", "WATCHDOG_"))}
    env["PYTHONPATH"] = str(REPO_ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.Popen([sys.executable, "-m", "bms_estimator.cli", "run", "--config", str(cfg)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    try:
        yield proc, LogReader(proc), cfg, state
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_sighup_with_a_bad_config_keeps_running_and_a_good_one_reloads(daemon):
    proc, logs, cfg, state = daemon
    logs.wait_for("can bus open: receiving")

    write_config(cfg, state, n_cells=0)  # no longer valid
    proc.send_signal(signal.SIGHUP)
    refused = logs.wait_for("configuration not reloaded: the service goes on with the one it has")[0]
    assert proc.poll() is None, "a SIGHUP ended the service"
    assert any("pack.n_cells" in p for p in refused["problems"]), refused
    assert refused["config"] == str(cfg)

    write_config(cfg, state, level="DEBUG")
    proc.send_signal(signal.SIGHUP)
    reloaded = logs.wait_for("configuration reloaded")[0]
    assert reloaded["settings"]["logging"]["level"] == "DEBUG"  # what runs now, secrets redacted
    logs.wait_for("can bus open: receiving", count=2)  # the service runs again, on the new configuration
    assert proc.poll() is None
    assert len(logs.wait_for("estimator state saved")) == 1  # the stop before the reload saved the state
    assert [e for e in logs.events if e.get("level") == "debug"], "the new logging.level is not in force"

    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=15) == 0, "".join(logs.text[-30:])
    logs.wait_for("service stopped", count=2)
    assert load_state(state, pack_id=PACK, n_cells=N, max_age_s=None) is not None
    assert not [e for e in logs.events if e.get("level") in ("error", "critical")
                and "not reloaded" not in e.get("event", "")], logs.text


def test_systemd_hears_reloading_then_ready_and_a_stop_during_a_reload_stops(tmp_path, monkeypatch):
    """In process, with a notify socket: a reload says RELOADING=1 (never STOPPING=1, which would tell
    systemd the unit is going down) and then READY=1 from the new service, which resumes the state the
    old one saved. SIGTERM while the next configuration is being built (its files on a hung mount, say): the running
    service stops at once (STOPPING=1, state saved), not waiting for the build, and the new one never
    runs; a second stop changes nothing."""
    import asyncio

    from service_helpers import NotifySocket, run_async, wait_until
    from test_daemon import make_cfg

    from bms_estimator.service.daemon import Service, serve

    srv = NotifySocket(tmp_path / "notify.sock", monkeypatch)

    def said() -> list[str]:
        return [m.splitlines()[0] for m in srv.drain()]

    cfg = make_cfg(tmp_path, f"bmsr-{uuid.uuid4().hex[:8]}", health={"enabled": False})
    building, release, finished = threading.Event(), threading.Event(), threading.Event()
    built: list[Service] = []

    def rebuild() -> Service:
        if built:  # the second reload: a stop arrives while it is built (its files on a hung mount)
            building.set()
            release.wait(10)
            finished.set()
        built.append(Service(cfg))
        return built[-1]

    async def main():
        svc = Service(cfg)
        stop, reload = asyncio.Event(), asyncio.Event()
        task = asyncio.create_task(serve(svc, stop, reload, rebuild))
        await wait_until(svc.ready.is_set, 10, "ready")
        reload.set()
        await wait_until(lambda: built and built[0].ready.is_set(), 10, "the reloaded service ready")
        first = said()
        reload.set()
        await wait_until(building.is_set, 10, "the second rebuild under way")
        stop.set()
        stop.set()  # a second SIGTERM
        ended = await asyncio.wait_for(task, 15)
        stopped_while_building = not finished.is_set()
        release.set()
        await wait_until(lambda: len(built) == 2, 10, "the abandoned rebuild to return")
        return first, ended, stopped_while_building

    try:
        first, ended, stopped_while_building = run_async(main(), 30)
        last = said()[len(first):]
    finally:
        srv.close()
    assert [m for m in first if m != "WATCHDOG=1" and not m.startswith("STATUS=")] == \
        ["READY=1", "RELOADING=1", "READY=1"], first
    assert built[0].restored  # the state the first service saved at the reload
    assert ended is built[0] and not ended.reloading
    assert stopped_while_building, "the stop waited for the configuration being read"
    assert "STOPPING=1" in last and "RELOADING=1" not in last, last
    assert len(built) == 2 and built[1].bus is None  # built, never run
    assert load_state(cfg.state.path, pack_id=cfg.pack.pack_id, n_cells=cfg.pack.n_cells, max_age_s=None) is not None


def test_a_sighup_while_the_service_starts_is_a_reload_once_it_runs(daemon):
    """The loop's handlers are installed after the configuration, DBC and OCV table are loaded (about a
    second). A SIGHUP before that (``systemctl kill -s HUP``, a config tool) ended the process, and
    systemd counts a death by SIGHUP as a clean exit: ``Restart=on-failure`` left the estimator down.
    Now it is held and served as a reload once the service runs."""
    proc, logs, cfg, state = daemon
    logs.wait_for("can.mapping.cells_beyond_pack")  # the decoder is being built: no handler yet
    proc.send_signal(signal.SIGHUP)
    logs.wait_for("configuration reloaded")
    logs.wait_for("can bus open: receiving", count=2)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=15) == 0, "".join(logs.text[-10:])


def test_after_a_reload_the_service_before_is_collected_and_the_new_one_frozen():
    """The daemon keeps what lives for ever out of the cyclic GC (``gc.freeze``) at start and after each
    reload.  A service is a reference cycle: frozen, it outlived every collection, and before this each
    reload left the new service unfrozen (full collections over its DBC stalling ticks) or, frozen
    without unfreezing first, kept the old one for good (measured 1.4 MiB a reload)."""
    import gc
    import weakref

    from bms_estimator.cli.run import freeze_long_lived
    from bms_estimator.service.config import load_config
    from bms_estimator.service.daemon import Service

    try:
        old = Service(load_config(None))
        gone = weakref.ref(old)
        freeze_long_lived()
        del old
        gc.collect()
        assert gone() is not None  # frozen: no collection looks at it (what keeps ticks free of stalls)
        new = Service(load_config(None))
        freeze_long_lived()  # what the reload does
        assert gone() is None
        kept = weakref.ref(new)
        del new
        gc.collect()
        assert kept() is not None  # the new one frozen in its turn
    finally:
        gc.unfreeze()  # the test process as it was


def test_a_reload_whose_state_save_fails_resumes_the_state_from_memory(tmp_path, monkeypatch):
    """A reload hands the state over through the state file. Where that save failed (a read-only
    remount, a full disk), the new service resumed the last file that was written, up to hours
    old, or started fresh: the coulomb count since then was lost without a word beyond the failed
    save. Now the new service resumes the old one's state from memory, when it has the same
    estimator configuration (the fingerprint a file must have been made with)."""
    import asyncio
    import errno

    import numpy as np
    from service_helpers import run_async, wait_until
    from test_daemon import VBus, make_cfg, rows, wait_samples

    from bms_estimator.service import daemon as daemon_mod
    from bms_estimator.service.daemon import Service, serve

    def read_only(*_a, **_kw):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(daemon_mod, "save_state", read_only)
    ch = f"bmsr-{uuid.uuid4().hex[:8]}"
    cfg = make_cfg(tmp_path, ch, health={"enabled": False})
    built: list[Service] = []

    def rebuild() -> Service:
        built.append(Service(cfg))
        return built[-1]

    async def main():
        vb = VBus(ch)
        svc = Service(cfg)
        stop, reload = asyncio.Event(), asyncio.Event()
        task = asyncio.create_task(serve(svc, stop, reload, rebuild))
        try:
            await wait_until(svc.ready.is_set, 10, "ready")
            vb.send(rows(0, 30))
            await wait_samples(svc, 30)
            before = (svc.estimator.soc.copy(), svc.estimator.samples)
            reload.set()
            await wait_until(lambda: built and built[0].ready.is_set(), 10, "the reloaded service ready")
            after = (built[0].estimator.soc.copy(), built[0].estimator.samples)
            restored = built[0].restored
        finally:
            stop.set()
            await asyncio.wait_for(task, 15)
            vb.shutdown()
        return before, after, restored

    from structlog.testing import capture_logs

    with capture_logs() as logs:
        before, after, restored = run_async(main(), 40)
    assert not cfg.state.path.exists()  # no save ever reached the disk
    assert restored and after[1] == before[1] == 30
    # the failed final save is a warning (the count since the last save is at stake), not news
    failed = [e for e in logs if e.get("event") == "final state save failed"]
    assert failed and all(e["log_level"] == "warning" for e in failed), failed
    np.testing.assert_array_equal(after[0], before[0])


def test_a_reload_keeps_home_assistant_online_unless_the_availability_topic_moves(mosquitto, tmp_path):
    """A reload stopped the running service as SIGTERM does, publishing ``offline``: every Home
    Assistant entity of the pack turned unavailable for the second the new service took to connect.
    A reload that keeps the broker and availability topic now leaves ``online`` standing; one that
    moves it (another ``base_topic``) still says ``offline`` on the old topic, and a stop still does."""
    import asyncio

    from service_helpers import Collector, run_async, wait_until
    from test_daemon import make_cfg

    from bms_estimator.service.daemon import Service, serve

    ch = f"bmsr-{uuid.uuid4().hex[:8]}"
    cfgs = [make_cfg(tmp_path, ch, mqtt_port=mosquitto.port, health={"enabled": False}),
            make_cfg(tmp_path, ch, mqtt_port=mosquitto.port, health={"enabled": False}, mqtt={"base_topic": "moved"})]
    built: list[Service] = []

    def rebuild() -> Service:
        built.append(Service(cfgs[len(built)]))
        return built[-1]

    first = Service(make_cfg(tmp_path, ch, mqtt_port=mosquitto.port, health={"enabled": False}))
    old, new = first.publisher.availability_topic, Service(cfgs[1]).publisher.availability_topic
    assert old != new

    async def main():
        async with Collector(mosquitto.port, (old, new)) as col:
            stop, reload = asyncio.Event(), asyncio.Event()
            task = asyncio.create_task(serve(first, stop, reload, rebuild))
            await col.wait(lambda c: c.payloads(old) == ["online"], 10, "online")
            reload.set()  # the same configuration
            await wait_until(lambda: built and built[0].publisher.connected, 10, "the reloaded service connected")
            await col.wait(lambda c: len(c.payloads(old)) >= 2, 10, "the reloaded service's online")
            same = col.payloads(old)
            reload.set()  # base_topic moved
            await wait_until(lambda: len(built) == 2 and built[1].publisher.connected, 10, "the moved service connected")
            await col.wait(lambda c: c.payloads(new) == ["online"] and len(c.payloads(old)) > len(same), 10, "moved")
            moved = col.payloads(old)
            stop.set()
            await asyncio.wait_for(task, 15)
            await col.wait(lambda c: c.payloads(new)[-1:] == ["offline"], 10, "offline at the stop")
            return same, moved, col.payloads(new)

    same, moved, last = run_async(main(), 60)
    assert same == ["online", "online"], same  # no offline between: the entities stayed available
    assert moved == ["online", "online", "offline"], moved  # the old topic told it is left
    assert last == ["online", "offline"], last
