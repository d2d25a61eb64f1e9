"""MqttPublisher against a real Mosquitto broker."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from service_helpers import (
    Collector,
    client_tls_context,
    free_port,
    make_tls_files,
    retained,
    run_async,
    wait_until,
)

from bms_estimator.service.config import MqttConfig
from bms_estimator.service.metrics import ServiceMetrics
from bms_estimator.service.mqtt import MqttPublisher

REPO_ROOT = Path(__file__).resolve().parents[2]


def mqtt_cfg(port: int, **kw) -> MqttConfig:
    base = dict(
        host="127.0.0.1",
        port=port,
        reconnect_min_s=0.05,
        reconnect_max_s=0.2,
        timeout_s=3.0,
        keepalive=10,
    )
    base.update(kw)
    return MqttConfig(**base)


def cell_arrays(n: int, t: float) -> dict[str, np.ndarray]:
    i = np.arange(n, dtype=float)
    return {
        "soc": 0.5 + 0.01 * i,
        "r0_ohm": 0.001 * (1 + i),
        "r1_ohm": np.full(n, 0.002),
        "c1_f": np.full(n, 1000.0),
        "r2_ohm": np.full(n, 0.003),
        "c2_f": np.full(n, 20000.0),
        "c0_v": np.full(n, t),  # lets a test tell submissions apart
        "stale": np.arange(n) % 2 == 1,
    }


@contextlib.asynccontextmanager
async def running(pub: MqttPublisher):
    task = asyncio.create_task(pub.run())
    try:
        yield task
    finally:
        await pub.close(timeout_s=3.0)
        assert task.done()
        # run() ended by close(): no exception, no cancellation.
        assert not task.cancelled()
        assert task.exception() is None


@pytest.mark.parametrize("qos", [0, 2])
def test_states_arrive_as_json_with_availability(mosquitto, qos):
    port = mosquitto.port
    n = 3

    async def main():
        metrics = ServiceMetrics()
        pub = MqttPublisher(mqtt_cfg(port, qos=qos, discovery=False), f"p{qos}", n, metrics=metrics)
        async with Collector(port, ("bms/#",), qos=2) as col:
            async with running(pub):
                await wait_until(lambda: pub.connected, 5, "publisher connected")
                arrays = cell_arrays(n, 1.0)
                arrays["r0_ohm"][2] = math.nan
                pub.submit_cells(12.5, arrays)
                pub.submit_pack({"t_s": 12.5, "soc_min": np.float64(0.5), "soc_max": 0.52, "soc_mean": 0.51,
                                 "current_a": -3.25, "cells_stale": 1, "samples": np.int64(7)})
                await col.wait(
                    lambda c: all(c.on(pub.cell_topic(i)) for i in range(n)) and c.on(pub.pack_topic),
                    what="cell and pack states",
                )
                for i in range(n):
                    (msg,) = col.on(f"bms/p{qos}/cell/{i}/state")
                    assert msg.qos == qos
                    assert not msg.retain
                    st = json.loads(msg.payload)
                    assert st["t_s"] == 12.5
                    assert st["soc"] == pytest.approx(0.5 + 0.01 * i)
                    assert st["r1_ohm"] == 0.002 and st["c1_f"] == 1000.0
                    assert st["tau1_s"] == pytest.approx(2.0)  # derived R1*C1
                    assert st["tau2_s"] == pytest.approx(60.0)
                    assert st["c0_v"] == 1.0
                    assert st["stale"] is (i % 2 == 1)
                    assert set(st) >= {"soc", "r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "c0_v",
                                       "tau1_s", "tau2_s", "stale", "t_s"}
                assert json.loads(col.on(f"bms/p{qos}/cell/2/state")[0].payload)["r0_ohm"] is None  # NaN -> null
                pack = json.loads(col.on(f"bms/p{qos}/pack/state")[0].payload)
                assert pack["soc_min"] == pytest.approx(0.5) and pack["soc_max"] == pytest.approx(0.52)
                assert pack["soc_mean"] == pytest.approx(0.51)
                assert pack["current_a"] == -3.25 and pack["cells_stale"] == 1 and pack["samples"] == 7

                online = await retained(port, f"bms/p{qos}/availability")
                assert online is not None and online.payload == b"online" and online.retain
                assert online.qos == 1  # availability is QoS 1 whatever the telemetry's QoS

            # close() published "offline" itself (retained) and disconnected cleanly.
            offline = await retained(port, f"bms/p{qos}/availability")
            assert offline is not None and offline.payload == b"offline"
            assert col.payloads(f"bms/p{qos}/availability")[-1] == "offline"
        c = pub.counters
        assert c.connects == 1 and c.connect_failures == 0 and c.dropped == 0
        assert c.published == n + 1 + 2  # states + pack + online + offline
        value = metrics.registry.get_sample_value
        assert value("bms_mqtt_published_total") == c.published and value("bms_mqtt_connects_total") == 1
        assert value("bms_mqtt_connected") == 0
        assert value("bms_mqtt_publish_latency_seconds_count") == n + 1  # the states, not availability

    run_async(main())


def test_home_assistant_discovery_retained_and_resent(mosquitto):
    port = mosquitto.port
    n = 2
    # pack: SOC min/mean/max, current, stale cells, cells at a capacity bound, voltage, capacity, state; per
    # cell: SOC, R0, voltage, temperature, capacity
    n_configs = 9 + 6 * n  # per cell: SOC, its uncertainty, R0, voltage, temperature, capacity
    # SOP/SOE/SOH (issue 14): pack 10 s current limits (2), power limits at 2/10/30 s (6), energy left,
    # delivered, discharged, time to empty and full, capacity and resistance SOH (7); per cell the 10 s
    # power limits, the energy left and both SOH figures
    n_configs += 15 + 5 * n

    async def main():
        pub = MqttPublisher(mqtt_cfg(port, qos=0), "hapack", n, expire_after_s=30)
        async with running(pub):
            await wait_until(lambda: pub.counters.published >= 1 + n_configs, 5, "discovery published")
            async with Collector(port, ("homeassistant/sensor/#",), qos=1) as col:
                await col.wait(lambda c: len(c.messages) >= n_configs, what="retained discovery")
                assert all(m.retain and m.qos == 1 for m in col.messages)
                configs = {m.topic.value: json.loads(m.payload) for m in col.messages}
                assert len(configs) == n_configs
                soc = configs["homeassistant/sensor/bms_hapack_cell1_soc/config"]
                assert soc["state_topic"] == "bms/hapack/cell/1/state"
                assert soc["unique_id"] == "bms_hapack_cell1_soc"
                assert soc["unit_of_measurement"] == "%" and soc["device_class"] == "battery"
                assert "value_json.soc" in soc["value_template"] and "round" not in soc["value_template"]
                assert soc["suggested_display_precision"] == 1
                assert soc["device"]["identifiers"] == ["bms_estimator_hapack"]
                assert soc["origin"]["name"] == "bms-estimator"
                # per cell: disabled by default, unavailable while stale or offline, expiring
                assert soc["enabled_by_default"] is False and soc["expire_after"] == 30
                assert soc["availability_mode"] == "all"
                assert {"topic": "bms/hapack/availability"} in soc["availability"]
                r0 = configs["homeassistant/sensor/bms_hapack_cell0_r0/config"]
                assert "value_json.r0_ohm" in r0["value_template"] and r0["unit_of_measurement"] == "mΩ"
                for key in ("voltage", "temperature", "capacity"):
                    assert f"homeassistant/sensor/bms_hapack_cell0_{key}/config" in configs
                cur = configs["homeassistant/sensor/bms_hapack_pack_current/config"]
                assert cur["state_topic"] == "bms/hapack/pack/state" and cur["device_class"] == "current"
                assert cur["availability_topic"] == "bms/hapack/availability" and "enabled_by_default" not in cur
                volt = configs["homeassistant/sensor/bms_hapack_pack_voltage/config"]
                assert volt["device_class"] == "voltage" and "value_json.pack_voltage_v" in volt["value_template"]
                p10 = configs["homeassistant/sensor/bms_hapack_pack_p_discharge_max_10s_w/config"]
                assert p10["device_class"] == "power" and p10["unit_of_measurement"] == "W"
                assert "value_json.p_discharge_max_10s_w" in p10["value_template"]
                left = configs["homeassistant/sensor/bms_hapack_pack_energy_left_wh/config"]
                assert left["unit_of_measurement"] == "Wh" and left["device_class"] == "energy_storage"
                net = configs["homeassistant/sensor/bms_hapack_pack_energy_delivered_wh/config"]
                assert net["device_class"] == "energy" and net["state_class"] == "total"
                soh = configs["homeassistant/sensor/bms_hapack_cell1_soh_capacity/config"]
                assert soh["unit_of_measurement"] == "%" and "* 100" in soh["value_template"]
                state = configs["homeassistant/sensor/bms_hapack_pack_state/config"]
                assert state["device_class"] == "enum" and "running" in state["options"]
                assert {c["device"]["identifiers"][0] for c in configs.values()} == {"bms_estimator_hapack"}

                # Home Assistant restarts: every config is sent again (live, not retained copies).
                col.messages.clear()
                await col.client.publish("homeassistant/status", "offline", qos=1)
                await asyncio.sleep(0.3)
                assert col.messages == []  # "offline" triggers nothing
                await col.client.publish("homeassistant/status", "online", qos=1)
                await col.wait(lambda c: len(c.messages) >= n_configs, what="discovery re-sent")
                assert {m.topic.value for m in col.messages} == set(configs)
                assert not any(m.retain for m in col.messages)  # fresh publishes to a live subscriber

                # A flood of "online" (issue 16: one INFO line and one discovery each) is coalesced
                # into one delayed re-send.
                pub.HA_ONLINE_MIN_INTERVAL_S = 1.0
                await asyncio.sleep(1.0)
                col.messages.clear()
                for _ in range(20):
                    await col.client.publish("homeassistant/status", "online", qos=1)
                await col.wait(lambda c: len(c.messages) >= n_configs, what="discovery re-sent once")
                await asyncio.sleep(0.3)
                assert len(col.messages) == n_configs  # the other 19 wait for the interval
                await col.wait(lambda c: len(c.messages) >= 2 * n_configs, what="the coalesced re-send", timeout=5)
                await asyncio.sleep(1.5)
                assert len(col.messages) == 2 * n_configs  # and no more

    run_async(main())


async def _retained_configs(port: int) -> dict[str, dict]:
    """Every retained discovery config on the broker (collected up to a probe of our own)."""
    async with Collector(port, ("homeassistant/#", "probe/#"), qos=1) as col:
        await col.client.publish("probe/x", "p", qos=1)
        await col.wait(lambda c: bool(c.on("probe/x")), what="probe")
        return {m.topic.value: json.loads(m.payload) for m in col.messages
                if m.retain and m.topic.value.startswith("homeassistant/") and m.payload}


def test_orphan_entities_are_removed(mosquitto):
    """A restart with fewer cells removes the entities of the cells that are gone; discovery
    turned off removes them all; another pack's entities (even one whose id starts alike) stay."""
    port = mosquitto.port

    async def publish_once(pack: str, n: int, **kw) -> MqttPublisher:
        pub = MqttPublisher(mqtt_cfg(port, **kw), pack, n)
        async with running(pub):
            await wait_until(lambda: pub._orphans_checked and pub.counters.published >= 1, 5, "connected")
            if kw.get("discovery", True):
                await wait_until(lambda: pub.counters.published >= 1 + len(pub.discovery_messages()), 5, "discovery")
        return pub

    async def main():
        await publish_once("hapack_x", 1)
        await publish_once("hapack", 4)
        before = await _retained_configs(port)
        assert "homeassistant/sensor/bms_hapack_cell3_soc/config" in before
        await publish_once("hapack", 2)
        after = await _retained_configs(port)
        ours = {t for t in after if "/bms_hapack_" in t and "/bms_hapack_x_" not in t}
        assert not any(f"_cell{i}_" in t for t in ours for i in (2, 3))
        assert "homeassistant/sensor/bms_hapack_cell1_soc/config" in ours
        assert len(ours) == 9 + 15 + (6 + 5) * 2  # with the SOP/SOE/SOH entities (issue 14)
        await publish_once("hapack", 2, discovery=False)
        after = await _retained_configs(port)
        assert not any("/bms_hapack_" in t and "/bms_hapack_x_" not in t for t in after)
        assert len([t for t in after if "/bms_hapack_x_" in t]) == 9 + 15 + 6 + 5  # the other pack kept

    run_async(main())


def test_a_pack_whose_id_extends_another_keeps_its_entities(mosquitto):
    """Pack "rack" must not take pack "rack_pack"'s entities (bms_rack_pack_pack_*) or pack "rack_cell1"'s
    (bms_rack_cell1_pack_*) for its own orphans. Before, a unique id counted as a pack's when it went on with
    "pack_" or "cell<i>_" after the pack's prefix, so a start of "rack" cleared both other packs' entities
    from Home Assistant."""
    port = mosquitto.port

    async def publish_once(pack: str, n: int) -> MqttPublisher:
        pub = MqttPublisher(mqtt_cfg(port), pack, n)
        async with running(pub):
            await wait_until(lambda: pub.counters.published >= 1 + len(pub.discovery_messages()), 5, "discovery")
        return pub

    async def main():
        others = [await publish_once("rack_pack", 1), await publish_once("rack_cell1", 1)]
        rack = await publish_once("rack", 2)
        after = await _retained_configs(port)
        for pub in (*others, rack):
            assert {t for t, _ in pub.discovery_messages()} <= set(after), pub.pack_id

    run_async(main())


def test_a_big_pack_that_shrinks_has_its_orphan_entities_removed(broker_factory):
    """A 192-cell pack announces 2136 retained discovery configs (11 per cell, 24 for the pack), more than a
    broker queues for one client (Mosquitto's max_queued_messages, 1000 by default): a scan subscribed to
    every discovery config on the broker had the rest, and its own probe behind them, dropped by the broker,
    timed out, and removed nothing. Restarted with 96 cells, cells 96-191 stayed in Home Assistant for ever
    (and so did every orphan of any pack on a broker holding more than 1000 configs)."""
    port = broker_factory(extra_conf="max_queued_messages 1000").port  # Mosquitto's default (the tests' is deeper)

    async def publish_once(pack: str, n: int) -> MqttPublisher:
        pub = MqttPublisher(mqtt_cfg(port), pack, n)
        n_configs = len(pub.discovery_messages())  # once: 2136 JSON configs take a while to build
        async with running(pub):
            await wait_until(lambda: pub._orphans_checked and pub.counters.published >= 1 + n_configs, 20,
                             "discovery")
        return pub

    def cell_topics(pack: str, cells) -> list[str]:
        return [f"homeassistant/sensor/bms_{pack}_cell{i}_{uid}/config" for i in cells
                for uid in ("soc", "voltage", "r0", "capacity", "soh_resistance")]

    async def retained(topics: list[str]) -> set[str]:
        async with Collector(port, (*topics, "probe/y"), qos=1) as col:
            await col.client.publish("probe/y", "p", qos=1)
            await col.wait(lambda c: bool(c.on("probe/y")), what="probe")
            return {m.topic.value for m in col.messages if m.retain and m.payload}

    async def main():
        big = await publish_once("bigpack", 192)
        assert len(big.discovery_messages()) == 2136
        gone, kept = cell_topics("bigpack", (96, 150, 191)), cell_topics("bigpack", (0, 95))
        assert await retained(gone + kept) == set(gone + kept)
        await publish_once("bigpack", 96)
        assert await retained(gone + kept) == set(kept)

    run_async(main())


def test_publish_period_and_soc_deadband():
    """Telemetry thinning on the frames' time: a period per topic, and a SOC deadband with a
    longest silence; a stale flag that changes is always sent."""
    from types import SimpleNamespace

    n = 3
    pub = MqttPublisher(mqtt_cfg(1, publish_period_s=5.0, soc_deadband=0.01, max_period_s=20.0), "thin", n)
    sent: list[list[str]] = []
    pub._put = lambda items: sent.append([t for t, _, _ in items])

    def snap(t: float, soc: list[float], valid: list[bool] | None = None):
        from bms_estimator.service import schema

        v = np.array(valid if valid is not None else [True] * n)
        return SimpleNamespace(t_s=t, cells={"soc": np.array(soc)}, valid=v, n_cells=n, cells_valid=int(v.sum()),
                               soc=schema.soc_stats(soc), current_a=1.0, current_valid=True, pack_voltage_v=12.0,
                               capacity_ah_mean=3.0, state=schema.EstimatorState.RUNNING)

    pub.submit_snapshot(snap(0.0, [0.5, 0.5, 0.5]))
    assert sent[-1] == [*pub.topics.cells, pub.pack_topic]
    sent.clear()
    for t in (1.0, 2.0, 3.0, 4.0):  # within the period: nothing
        pub.submit_snapshot(snap(t, [0.6, 0.6, 0.6]))
    assert sent == []
    pub.submit_snapshot(snap(5.0, [0.505, 0.52, 0.5], [True, True, False]))
    # cell 0 moved less than the deadband; cell 1 moved; cell 2 went stale
    assert sent[-1] == [pub.topics.cells[1], pub.topics.cells[2], pub.pack_topic]
    pub.submit_snapshot(snap(20.0, [0.505, 0.52, 0.5], [True, True, False]))
    assert sent[-1] == [pub.topics.cells[0], pub.pack_topic]  # cell 0: silent for max_period_s
    assert pub.counters.submit_errors == 0


def test_final_snapshot_is_sent_whatever_the_period():
    """At a stop the newest state goes out even when publish_period_s/soc_deadband held it back
    (a thinned stream ends on the estimator's last state), once: topics already sent at that
    time are not repeated."""
    from types import SimpleNamespace

    from bms_estimator.service import schema

    n = 3
    pub = MqttPublisher(mqtt_cfg(1, publish_period_s=10.0, soc_deadband=0.01, max_period_s=60.0), "fin", n)
    sent: list[list[str]] = []
    pub._put = lambda items: sent.append([t for t, _, _ in items])

    def snap(t: float, soc: list[float]):
        v = np.ones(n, dtype=bool)
        return SimpleNamespace(t_s=t, cells={"soc": np.array(soc)}, valid=v, n_cells=n, cells_valid=n,
                               soc=schema.soc_stats(soc), current_a=1.0, current_valid=True, pack_voltage_v=12.0,
                               capacity_ah_mean=3.0, state=schema.EstimatorState.RUNNING)

    pub.submit_snapshot(snap(0.0, [0.5, 0.5, 0.5]))
    pub.submit_snapshot(snap(10.0, [0.6, 0.6, 0.5]))  # cells 0 and 1 moved: sent with the pack
    assert sent[-1] == [pub.topics.cells[0], pub.topics.cells[1], pub.pack_topic]
    sent.clear()
    pub.submit_snapshot(snap(13.0, [0.7, 0.7, 0.5]))  # within the period: held back
    assert sent == []
    pub.submit_snapshot(snap(13.0, [0.7, 0.7, 0.5]), final=True)
    assert sent == [[*pub.topics.cells, pub.pack_topic]]  # every cell, the unchanged one too
    pub.submit_snapshot(snap(13.0, [0.7, 0.7, 0.5]), final=True)  # already out at 13 s: nothing twice
    assert len(sent) == 1
    # after the final states the thinning goes on from them
    pub.submit_snapshot(snap(20.0, [0.8, 0.8, 0.8]))
    assert len(sent) == 1
    assert pub.counters.submit_errors == 0


def test_last_will_when_publisher_process_is_killed(mosquitto, tmp_path):
    port = mosquitto.port
    script = f"""
import asyncio, sys
sys.path.insert(0, {str(REPO_ROOT)!r})
from bms_estimator.service.config import MqttConfig
from bms_estimator.service.mqtt import MqttPublisher

async def main():
    cfg = MqttConfig(host="127.0.0.1", port={port}, discovery=False, qos=1, keepalive=30)
    pub = MqttPublisher(cfg, "willpack", 2)
    task = asyncio.create_task(pub.run())
    while not pub.connected:
        await asyncio.sleep(0.01)
    print("connected", flush=True)
    await task

asyncio.run(main())
"""
    errlog = tmp_path / "publisher.stderr"
    with errlog.open("wb") as err:
        proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=err)
    try:
        assert proc.stdout is not None
        # Wait (bounded) for the "connected" line; log lines may come first.
        deadline = time.monotonic() + 15
        seen = b""
        while b"connected\n" not in seen.replace(b"mqtt connected", b""):
            remaining = deadline - time.monotonic()
            ready, _, _ = select.select([proc.stdout], [], [], max(0.0, remaining))
            chunk = os.read(proc.stdout.fileno(), 4096) if ready else b""
            if not chunk:
                raise AssertionError(
                    f"publisher subprocess not connected: {seen!r} {errlog.read_text(errors='replace')}"
                )
            seen += chunk

        async def main():
            async with Collector(port, ("bms/willpack/availability",), qos=1) as col:
                await col.wait(lambda c: c.payloads("bms/willpack/availability") == ["online"], what="online")
                os.kill(proc.pid, signal.SIGKILL)  # no chance to publish or DISCONNECT
                proc.wait(timeout=5)
                await col.wait(lambda c: c.payloads("bms/willpack/availability")[-1:] == ["offline"],
                               what="last will")
            msg = await retained(port, "bms/willpack/availability")
            assert msg is not None and msg.payload == b"offline" and msg.retain

        run_async(main())
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=5)
        if proc.stdout:
            proc.stdout.close()


def test_cancel_publishes_offline_best_effort(mosquitto):
    port = mosquitto.port

    async def main():
        pub = MqttPublisher(mqtt_cfg(port, discovery=False), "cancelpack", 1)
        task = asyncio.create_task(pub.run())
        await wait_until(lambda: pub.connected, 5, "connected")
        task.cancel()
        # a bound, not a speed goal: the client's disconnect after the best-effort 'offline' took
        # over 5 s on this 2-core machine with other test runs loading it
        done, _ = await asyncio.wait({task}, timeout=30)
        assert done and task.cancelled()  # the cancellation is not swallowed
        msg = await retained(port, "bms/cancelpack/availability")
        assert msg is not None and msg.payload == b"offline"

    run_async(main())


def test_a_cancel_right_after_connecting_always_ends_the_publisher(mosquitto):
    """A cancel that lands as aiomqtt's 'online' publish completes was swallowed by Python 3.11's
    asyncio.wait_for (``bms_estimator.aio``), and the publisher then waited for ever. Against the
    code before the fix this test failed 3 runs of 3 on this 2-core machine; with two busy
    processes beside it each of 5 runs of 30 such cancels hung (at the 1st to 18th), and after
    the fix none of 480 did."""
    port = mosquitto.port

    async def main():
        for k in range(30):
            pub = MqttPublisher(mqtt_cfg(port, discovery=False), f"cancel{k}", 1)
            task = asyncio.create_task(pub.run())
            await wait_until(lambda: pub.connected, 5, "connected")
            task.cancel()
            done, _ = await asyncio.wait({task}, timeout=10)
            assert done and task.cancelled(), f"cancel {k} did not end the publisher"

    run_async(main(), timeout=150)


def test_username_password(broker_factory, mosquitto_passwd, tmp_path):
    pwfile = tmp_path / "passwd"
    subprocess.run([mosquitto_passwd, "-b", "-c", str(pwfile), "bms", "s3cret-pw"], check=True,
                   capture_output=True, timeout=30)
    broker = broker_factory(f"password_file {pwfile}\n", anonymous=False)
    port = broker.port

    async def main():
        bad = MqttPublisher(mqtt_cfg(port, username="bms", password="wrong", discovery=False), "authpack", 1)
        async with running(bad):
            await wait_until(lambda: bad.counters.connect_failures >= 2, 5, "rejected connects")
            assert bad.counters.connects == 0 and not bad.connected

        good = MqttPublisher(mqtt_cfg(port, username="bms", password="s3cret-pw", discovery=False), "authpack", 1)
        async with Collector(port, ("bms/#",), username="bms", password="s3cret-pw") as col:
            async with running(good):
                await wait_until(lambda: good.connected, 5, "connected with password")
                good.submit_cells(1.0, {"soc": [0.7]})
                await col.wait(lambda c: c.on("bms/authpack/cell/0/state"), what="state")
            assert json.loads(col.on("bms/authpack/cell/0/state")[0].payload)["soc"] == 0.7
        assert good.counters.connect_failures == 0

    run_async(main())


def test_tls(broker_factory, tmp_path):
    files = make_tls_files(tmp_path / "tls")
    if files is None:
        pytest.skip("cannot generate a test certificate: neither the cryptography package nor openssl exists")
    broker = broker_factory(
        f"cafile {files['ca']}\ncertfile {files['cert']}\nkeyfile {files['key']}\n"
    )
    port = broker.port

    async def main():
        # Without the test CA the server certificate is not trusted.
        untrusted = MqttPublisher(mqtt_cfg(port, tls={"enabled": True}, discovery=False), "tlspack", 1)
        async with running(untrusted):
            await wait_until(lambda: untrusted.counters.connect_failures >= 1, 5, "TLS verify failure")
            assert untrusted.counters.connects == 0

        pub = MqttPublisher(
            mqtt_cfg(port, tls={"enabled": True, "ca_file": str(files["ca"])}, discovery=False), "tlspack", 1
        )
        async with Collector(port, ("bms/#",), tls_context=client_tls_context(files["ca"])) as col:
            async with running(pub):
                await wait_until(lambda: pub.connected, 5, "TLS connected")
                pub.submit_cells(2.0, {"soc": [0.25]})
                await col.wait(lambda c: c.on("bms/tlspack/cell/0/state"), what="state over TLS")
        assert json.loads(col.on("bms/tlspack/cell/0/state")[0].payload)["soc"] == 0.25

    run_async(main())


def test_broker_down_at_start_then_up_delivers_newest(broker_factory):
    # A persistent subscriber session (restored by the broker's persistence
    # across its restart) receives what is published while it is offline,
    # so nothing depends on who reconnects first.
    broker = broker_factory(persistence=True)
    port = broker.port
    n = 3
    sub_kw = dict(identifier="down-start-collector", clean_session=False)

    async def main():
        async with Collector(port, ("bms/dstart/cell/#",), qos=1, **sub_kw):
            pass
        broker.stop()

        pub = MqttPublisher(mqtt_cfg(port, qos=1, discovery=False), "dstart", n)
        async with running(pub):
            await wait_until(lambda: pub.counters.connect_failures >= 2, 5, "failed connects")
            for t in (1.0, 2.0, 3.0):
                pub.submit_cells(t, cell_arrays(n, t))  # must neither raise nor block
            assert pub.buffered == n
            assert pub.counters.dropped == 2 * n  # two older states per cell superseded
            assert not pub.connected

            broker.start()
            await wait_until(lambda: pub.connected and pub.buffered == 0, 10, "reconnect and flush")
            await wait_until(lambda: pub.counters.published >= 1 + n, 5, "states published")
            assert pub.counters.connects == 1

        async with Collector(port, ("bms/dstart/cell/#",), qos=1, **sub_kw) as col:
            await col.wait(lambda c: len(c.messages) >= n, what="queued states")
            await asyncio.sleep(0.2)
            by_cell = {m.topic.value: json.loads(m.payload) for m in col.messages}
            assert len(col.messages) == n  # only the newest state per cell
            assert {s["t_s"] for s in by_cell.values()} == {3.0}
            assert {s["c0_v"] for s in by_cell.values()} == {3.0}

    run_async(main(), timeout=40)


def test_broker_down_mid_run_and_back(broker_factory):
    broker = broker_factory()
    port = broker.port
    n = 2

    async def main():
        metrics = ServiceMetrics()
        pub = MqttPublisher(mqtt_cfg(port, qos=1, discovery=False), "midrun", n, metrics=metrics)
        clock = {"t": 0.0}

        async def ticker():
            while True:
                clock["t"] += 1.0
                pub.submit_cells(clock["t"], cell_arrays(n, clock["t"]))
                await asyncio.sleep(0.02)

        async with running(pub) as task:
            tick = asyncio.create_task(ticker())
            try:
                async with Collector(port, ("bms/midrun/#",), qos=1) as col:
                    await col.wait(lambda c: len(c.on("bms/midrun/cell/1/state")) >= 3, what="live states")
                broker.stop()
                await wait_until(lambda: not pub.connected, 5, "disconnect noticed")
                dropped_before = pub.counters.dropped
                await wait_until(lambda: pub.counters.connect_failures >= 2, 5, "failed reconnects")
                await asyncio.sleep(0.2)
                assert not task.done()  # no exception escaped run()
                assert pub.counters.dropped > dropped_before  # states superseded while down
                assert pub.buffered <= n
                assert pub.counters.disconnects == 1

                t_restart = clock["t"]
                broker.start()
                await wait_until(lambda: pub.counters.connects == 2, 10, "reconnected")
                async with Collector(port, ("bms/midrun/#",), qos=1) as col:
                    await col.wait(
                        lambda c: any(json.loads(m.payload)["t_s"] > t_restart
                                      for m in c.on("bms/midrun/cell/0/state")),
                        what="fresh states after reconnect",
                    )
                    assert col.payloads("bms/midrun/availability") == ["online"]  # retained, re-published
            finally:
                tick.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await tick
        value = metrics.registry.get_sample_value
        assert value("bms_mqtt_connect_failures_total") == pub.counters.connect_failures >= 2
        assert value("bms_mqtt_dropped_total") == pub.counters.dropped

    run_async(main(), timeout=40)


def test_backoff_grows_and_is_bounded():
    # Broker absent: count attempts over a fixed window with min=0.05, max=0.2.
    port = free_port()

    async def main():
        pub = MqttPublisher(mqtt_cfg(port, reconnect_min_s=0.05, reconnect_max_s=0.2), "bo", 1)
        delays = [pub._backoff(k) for k in range(1, 12)]
        assert all(0.05 <= d <= 0.2 for d in delays)
        assert max(delays[:1]) <= 0.05 + 1e-9 and min(delays[6:]) >= 0.1  # grows to max, jittered
        t0 = time.monotonic()
        async with running(pub):
            await asyncio.sleep(1.0)
        elapsed = time.monotonic() - t0
        # Without back-off a refused localhost connect loops thousands of times a second;
        # with it: at most 1.0/0.05 + 1 attempts, and at least 1.0/0.2 - 1.
        assert 3 <= pub.counters.connect_failures <= 21
        assert elapsed < 2.0  # close() returned promptly while disconnected

    run_async(main())


def test_buffer_is_bounded_and_submit_never_raises():
    cfg = mqtt_cfg(free_port(), buffer_max=5)
    pub = MqttPublisher(cfg, "buf", 10)  # never run: everything stays buffered
    pub.submit_cells(1.0, {"soc": np.linspace(0, 1, 10)})
    assert pub.buffered == 5 and pub.counters.dropped == 5  # 5 oldest cells evicted
    pub.submit_cells(2.0, {"soc": np.linspace(0, 1, 10)})
    assert pub.buffered == 5 and pub.counters.dropped == 15
    pub.submit_pack({"soc_mean": np.float32(0.5), "x": math.inf, "arr": np.array([1.0, math.nan])})
    assert pub.buffered == 5 and pub.counters.dropped == 16
    items = {t: p for t, p, _ in pub._buffer.pop_all()}
    assert set(items) == {f"bms/buf/cell/{i}/state" for i in (6, 7, 8, 9)} | {"bms/buf/pack/state"}
    assert json.loads(items["bms/buf/cell/9/state"])["t_s"] == 2.0  # newest kept
    # numpy scalars converted, non-finite -> null (strict JSON)
    assert json.loads(items["bms/buf/pack/state"]) == {"soc_mean": 0.5, "x": None, "arr": [1.0, None]}

    # Bad input is counted and logged, never raised, and queues nothing.
    pub.submit_cells(3.0, {"soc": [0.1, 0.2]})  # wrong length
    pub.submit_cells(3.0, {"soc": object()})  # not numeric
    pub.submit_cells(3.0, None)  # type: ignore[arg-type]
    pub.submit_pack(None)  # type: ignore[arg-type]
    assert pub.counters.submit_errors == 4
    assert pub.buffered == 0


def test_disabled_publisher_is_inert():
    pub = MqttPublisher(mqtt_cfg(free_port(), enabled=False), "off", 2)
    pub.submit_cells(1.0, {"soc": [0.1, 0.2]})
    assert pub.buffered == 0

    async def main():
        await asyncio.wait_for(pub.run(), 1.0)  # returns at once
        await pub.close()

    run_async(main())


def test_a_socket_closed_before_its_registration_logs_no_asyncio_error():
    """The spurious 'add_writer ... Bad file descriptor' on a reconnect (issue 16): paho reports
    its socket from the connecting thread, aiomqtt defers the selector registration, and the
    connection breaks (socket closed) before the loop runs it. aiomqtt's own client makes asyncio
    log that at ERROR; the service's client skips the registration of a socket that is gone, and
    still registers a live one."""
    import asyncio
    import socket as socketlib

    import aiomqtt

    from bms_estimator.service.mqtt_client import MqttClient

    async def closed_before_registration(cls):
        loop = asyncio.get_running_loop()
        errors = []
        loop.set_exception_handler(lambda _loop, ctx: errors.append(f"{ctx.get('message')} {ctx.get('exception')!r}"))
        client = cls("127.0.0.1", 1)
        for register in (client._on_socket_register_write, client._on_socket_open):
            a, b = socketlib.socketpair()
            register(client._client, None, a)
            a.close()  # the connection broke before the loop ran the registration
            b.close()
            await asyncio.sleep(0.05)
        live, peer = socketlib.socketpair()
        client._on_socket_register_write(client._client, None, live)
        await asyncio.sleep(0.05)
        registered = loop._selector.get_key(live.fileno()) is not None  # the live one is watched
        loop.remove_writer(live.fileno())
        live.close()
        peer.close()
        if client._misc_task is not None:
            client._misc_task.cancel()
        return errors, registered

    errors, _ = asyncio.run(closed_before_registration(aiomqtt.Client))
    # the library's behaviour, the cause (should this fail, aiomqtt fixed it and MqttClient can go)
    assert any("Bad file descriptor" in e for e in errors)
    errors, registered = asyncio.run(closed_before_registration(MqttClient))
    assert errors == [] and registered


def test_a_dropped_connections_error_is_never_logged_as_a_lost_future_exception():
    """A connection the broker drops sets aiomqtt's ``_disconnected`` to "Unexpected disconnection"; where
    nothing read it before aiomqtt replaced the future (its next ``__aenter__``), the garbage collector
    logged "Future exception was never retrieved" with the traceback at ERROR (about one dropped
    connection in 20 under reconnect churn).  With MqttClient the exception is retrieved when set, for
    the future made in ``__init__`` and for the one ``__aenter__`` puts in its place; an awaiter still
    gets it."""
    import gc

    import aiomqtt
    from aiomqtt.exceptions import MqttCodeError

    from bms_estimator.service.mqtt_client import MqttClient

    async def dropped(cls):
        loop = asyncio.get_running_loop()
        lost = []
        loop.set_exception_handler(lambda _loop, ctx: lost.append(ctx.get("message")))
        client = cls("127.0.0.1", 1)
        client._disconnected.set_exception(MqttCodeError(7, "Unexpected disconnection"))
        await asyncio.sleep(0)
        client._disconnected = asyncio.Future()  # as aiomqtt's __aenter__ replaces a finished one
        client._disconnected.set_exception(MqttCodeError(7, "Unexpected disconnection"))
        await asyncio.sleep(0)
        with pytest.raises(MqttCodeError):
            await client._disconnected  # whoever awaits it still gets it
        client._disconnected = asyncio.Future()
        if client._misc_task is not None:
            client._misc_task.cancel()
        del client
        gc.collect()
        await asyncio.sleep(0)
        return lost

    lost = asyncio.run(dropped(aiomqtt.Client))
    assert any("never retrieved" in (m or "") for m in lost)  # the library's behaviour, the cause
    assert asyncio.run(dropped(MqttClient)) == []


def test_cell_payload_texts_are_the_per_cell_dumps_byte_for_byte():
    """The one-build-per-tick JSON (one encoder pass per column, a template per cell) gives exactly
    the text of building and dumping each cell's payload dict: NaN/inf as null, numpy and
    broadcast scalars, R*C for a missing tau, extra keys, stale flags, awkward floats."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from bms_estimator.service import schema

    floats = st.floats(allow_nan=True, allow_infinity=True, width=64)

    @settings(max_examples=60, deadline=None)
    @given(n=st.integers(1, 12), data=st.data())
    def check(n, data):
        cells = {"soc": np.array(data.draw(st.lists(floats, min_size=n, max_size=n))),
                 "r1_ohm": np.array(data.draw(st.lists(floats, min_size=n, max_size=n))),
                 "c1_f": np.float32(data.draw(st.floats(width=32))),  # a scalar, broadcast to every cell
                 "capacity_ah": 2.5,
                 "x_extra%s": np.arange(n),  # a key outside the schema, a % in it
                 "stale": np.array(data.draw(st.lists(st.booleans(), min_size=n, max_size=n)))}
        t_s = data.draw(floats)
        want = [schema.dumps(p) for p in schema.cell_payloads(t_s, cells, n)]
        assert schema.cell_payload_texts(t_s, cells, n) == want
        which = sorted(set(data.draw(st.lists(st.integers(0, n - 1), max_size=n))))
        assert schema.cell_payload_texts(t_s, cells, n, np.array(which, dtype=np.int64)) == [want[i] for i in which]
        assert all(json.loads(w)["t_s"] == schema.json_number(t_s) for w in want)

    check()
    with pytest.raises(ValueError, match="expected 3"):
        schema.cell_payload_texts(0.0, {"soc": np.zeros(2)}, 3)


def _collect_loop_errors() -> list[dict]:
    """The running loop's errors in callbacks ("Exception in callback ...": a traceback in the journal),
    collected instead of logged."""
    errors: list[dict] = []
    asyncio.get_running_loop().set_exception_handler(lambda _loop, ctx: errors.append(ctx))
    return errors


def _broker_socket(backlog: int):
    """A listening TCP socket on a free 127.0.0.1 port that plays a broker's end."""
    import socket

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(backlog)
    return srv


def test_a_stop_while_a_broker_does_not_answer_the_connect_closes_the_socket():
    """A broker that accepts the TCP connection and never answers CONNECT (hung, or a black hole
    behind a NAT): a stop cancels the connect (``close``'s timeout). aiomqtt then left paho's socket
    open and watched by the loop, its keepalive task running: kept until the keepalive expired, and
    when the peer reset it, ``on_disconnect`` raised ``CancelledError`` from the cancelled
    ``_connected`` future inside a loop callback ("Exception in callback ...", a traceback in the
    journal; after a reload the loop lives on). Now the socket is closed at the cancel: the peer sees
    EOF, and its reset later reaches nothing."""
    import socket

    async def main():
        loop = asyncio.get_running_loop()
        errors = _collect_loop_errors()
        srv = _broker_socket(1)
        srv.setblocking(False)
        pub = MqttPublisher(mqtt_cfg(srv.getsockname()[1], discovery=False, timeout_s=30.0, keepalive=30),
                            "hungbroker", 1)
        task = asyncio.create_task(pub.run())
        conn, _ = await asyncio.wait_for(loop.sock_accept(srv), 5)
        conn.setblocking(False)
        first = await asyncio.wait_for(loop.sock_recv(conn, 4096), 5)
        assert first[:1] == b"\x10"  # the CONNECT packet: the client waits for its CONNACK now
        await pub.close(timeout_s=0.05)  # a stop: the publisher does not end in time and is cancelled
        assert task.done()
        try:
            eof = await asyncio.wait_for(loop.sock_recv(conn, 4096), 3)
        except TimeoutError:
            eof = None
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        conn.close()  # a reset
        srv.close()
        for _ in range(20):  # let a callback on the client's socket run, if one is still registered
            await asyncio.sleep(0.01)
        return eof, errors

    eof, errors = run_async(main())
    assert eof == b"", "the client's socket stayed open after the cancelled connect"
    assert errors == [], [e.get("message") for e in errors]


def test_a_stop_while_the_tcp_connect_itself_still_runs_closes_the_socket_it_makes():
    """A stop that lands while paho's TCP connect still runs in aiomqtt's executor thread (a broker that
    does not accept in time: here its accept queue is full, so the kernel drops the SYN and the client
    retries it a second later). The cancel does not stop the thread: the connect completed after it,
    and its socket stayed open (the CONNECT sent, never closed) with the loop watching it. Now the
    thread closes the socket it made: the broker sees EOF."""
    import socket

    async def main():
        loop = asyncio.get_running_loop()
        errors = _collect_loop_errors()
        srv = _broker_socket(0)
        port = srv.getsockname()[1]
        fillers = []
        for _ in range(3):  # fill the accept queue (backlog 0 holds one; a SYN beyond it is dropped)
            f = socket.socket()
            f.setblocking(False)
            f.connect_ex(("127.0.0.1", port))
            fillers.append(f)
        await asyncio.sleep(0.2)
        pub = MqttPublisher(mqtt_cfg(port, discovery=False, timeout_s=30.0, keepalive=30), "slowaccept", 1)
        task = asyncio.create_task(pub.run())
        await asyncio.sleep(0.3)  # the client's SYN dropped: its connect waits in the thread
        await pub.close(timeout_s=0.05)  # a stop: cancelled while the thread still connects
        assert task.done()
        srv.setblocking(False)
        late = None
        deadline = loop.time() + 10.0
        while late is None and loop.time() < deadline:  # free the queue; the client's retried SYN gets in
            try:
                conn, _ = srv.accept()
            except BlockingIOError:
                await asyncio.sleep(0.05)
                continue
            conn.setblocking(False)
            try:
                first = await asyncio.wait_for(loop.sock_recv(conn, 4096), 0.3)
            except TimeoutError:
                first = None  # a filler: it sends nothing and stays open
            if first is not None:  # the client's: its CONNECT, or at once its end
                late = conn
            else:
                conn.close()
        assert late is not None, "the client's connect never reached the broker"
        rest = first
        while rest:  # what it sent (the CONNECT, if it got that far), then: the end, or silence
            try:
                rest = await asyncio.wait_for(loop.sock_recv(late, 4096), 3)
            except TimeoutError:
                rest = None
        late.close()
        srv.close()
        for f in fillers:
            f.close()
        return rest, errors

    rest, errors = run_async(main())
    assert rest == b"", "the socket of the connect that completed after the stop stayed open"
    assert errors == [], [e.get("message") for e in errors]


def test_connections_that_drop_at_once_back_off_as_failed_connects_do(monkeypatch):
    """A connection that the broker drops at once (another client with the same client id, e.g. a second
    gateway or a stale process for this pack: the broker kicks the older session each time) reset the
    back-off: both reconnected every reconnect_min_s for ever, each time re-sending discovery (thousands
    of retained messages for 200 cells) and logging three lines. Now only a connection that lasted
    reconnect_max_s resets it; shorter ones back off like failed connects."""
    from structlog.testing import capture_logs

    pub = MqttPublisher(mqtt_cfg(free_port(), reconnect_min_s=0.01, reconnect_max_s=0.64), "dup", 1)
    sessions = []

    async def dropped_at_once() -> bool:
        sessions.append(time.monotonic())
        return True  # connected, then lost

    monkeypatch.setattr(pub, "_session", dropped_at_once)

    async def main():
        task = asyncio.create_task(pub.run())
        await wait_until(lambda: len(sessions) >= 8, 10, "8 sessions")
        await pub.close(timeout_s=3.0)
        await task

    with capture_logs() as logs:
        run_async(main())
    delays = [r["in_s"] for r in logs if r["event"] == "mqtt reconnecting"][:7]
    # reconnect_min_s doubling, with jitter in [base/2, base]: 0.01, 0.02, ... 0.64
    assert all(0.005 * 2 ** k <= d <= 0.01 * 2 ** k for k, d in enumerate(delays)), delays


def test_a_broker_down_for_days_is_not_a_journal_line_every_attempt():
    """A vehicle out of coverage (or a broker taken down) is tried every reconnect_max_s for as long as it
    lasts: each failed connect logged a WARNING and an INFO, 2880 lines a day at the default 60 s, for
    weeks, pushing the rest of the journal out. Now the first 10 in a row are logged each, then one in
    100, and the connect that ends the outage says how many failed before it."""
    from structlog.testing import capture_logs

    port = free_port()  # nothing listens: refused
    pub = MqttPublisher(mqtt_cfg(port, reconnect_min_s=0.001, reconnect_max_s=0.002), "away", 1)

    async def main():
        task = asyncio.create_task(pub.run())
        await wait_until(lambda: pub.counters.connect_failures >= 250, 60, "250 failed connects")
        await pub.close(timeout_s=3.0)
        await task

    with capture_logs() as logs:
        run_async(main())
    failed = [r for r in logs if r["event"] == "mqtt connect failed"]
    retries = [r for r in logs if r["event"] == "mqtt reconnecting"]
    assert len(failed) == 12  # before: one per attempt, 250 or more
    assert [r["failures_in_a_row"] for r in failed] == [*range(1, 11), 100, 200]
    assert len(retries) == len(failed)
    assert pub.counters.connect_failures >= 250  # every attempt still counted (bms_mqtt_connect_failures)
