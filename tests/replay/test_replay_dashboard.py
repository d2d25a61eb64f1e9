"""dashboard: state from recorded MQTT messages, rendering, garbage, and a real Mosquitto."""

from __future__ import annotations

import asyncio
import json
import time

import aiomqtt
import pytest
from replay_helpers import MOSQUITTO, Broker, mosquitto_available
from rich.console import Console
from service_helpers import run_async, wait_until

from bms_estimator.cli.__main__ import main
from bms_estimator.replay.dashboard import DashboardState, parse_broker, render, run_dashboard
from types import SimpleNamespace


from bms_estimator.service import schema


def cell_payload(i: int, t_s: float = 100.0, stale: bool = False) -> str:
    """A cell state as the service publishes it (service/schema.py)."""
    values = {
        "soc": 0.80 + 0.01 * i, "r0_ohm": 0.020 + 0.000125 * i, "r1_ohm": 0.010, "c1_f": 1500.0,
        "r2_ohm": 0.015, "c2_f": 20000.0, "c0_v": 0.0025, "tau1_s": 15.0, "tau2_s": 300.0, "stale": stale,
    }
    (payload,) = schema.cell_payloads(t_s, values, 1)
    return schema.dumps(payload)


def recorded(pack: str = "p1") -> list[tuple[str, bytes, float]]:
    msgs = [(f"bms/{pack}/availability", b"online", 0.5)]
    msgs += [(f"bms/{pack}/cell/{i}/state", cell_payload(i, stale=(i == 2)).encode(), 1.0 + 0.1 * i) for i in range(4)]
    snap = SimpleNamespace(t_s=100.0, soc=schema.soc_stats([0.80, 0.81, 0.82, 0.83]), current_a=-2.5,
                           n_cells=4, cells_valid=3, pack_voltage_v=14.8, current_valid=True,
                           capacity_ah_mean=3.0, state=schema.EstimatorState.DEGRADED)
    msgs.append((f"bms/{pack}/pack/state", schema.dumps(schema.pack_payload(snap)).encode(), 2.0))
    return msgs


def text(state: DashboardState, width: int = 160, **kw) -> str:
    console = Console(record=True, width=width, color_system=None)
    console.print(render(state, **kw))
    return console.export_text()


def test_recorded_messages_make_the_table():
    state = DashboardState()
    assert state.apply_many(recorded()) == 6
    state.tick(6.0)
    out = text(state)
    assert "pack p1" in out and "online" in out
    assert "80.00 / 81.50 / 83.00 %" in out  # pack SOC min/mean/max
    assert "current -2.500 A" in out and "stale cells 1" in out
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.strip()[:1].isdigit()}
    assert rows["0"][:8] == ["0", "80.00", "20.000", "15.0", "300", "2.50", "no", "5.0"]
    assert rows["3"][:3] == ["3", "83.00", "20.375"]
    assert rows["2"][6] == "yes"  # the service's stale flag
    assert rows["3"][7] == "4.7"  # age of the last message: now - received
    state.apply("bms/p1/availability", b"offline", 7.0)
    assert "offline" in text(state)


def test_pack_state_of_power_energy_and_health_line():
    """The SOP/SOE/SOH figures of the pack payload (issue 14) get a line of their own, in kW, Wh,
    min and %; a garbage value is shown as '-' and counted, not a crash."""
    state = DashboardState()
    pack = {"t_s": 1.0, "soc_min": 0.5, "soc_mean": 0.5, "soc_max": 0.5, "current_a": -2.0, "cells_stale": 0,
            "p_discharge_max_10s_w": 12345.0, "i_discharge_max_10s_a": 60.5, "p_charge_max_10s_w": 4000.0,
            "i_charge_max_10s_a": 20.0, "energy_left_wh": 1500.4, "time_to_empty_s": 3600.0,
            "soh_capacity_min": 0.934, "soh_resistance_max": "oops"}
    state.apply("bms/p1/pack/state", json.dumps(pack).encode(), 1.0)
    out = text(state)
    assert "10 s power limit discharge 12.35 kW (60.5 A), charge 4.00 kW (20.0 A)" in out
    assert "energy left 1500 Wh" in out and "to empty 60 min" in out
    assert "SOH capacity 93.4 %, resistance - %" in out
    assert state.counters.invalid_fields == 1
    assert "p_charge_max_2s_w" not in out  # not among the generic extras


def test_garbage_is_ignored_and_counted():
    state = DashboardState(pack_id="p1")
    state.apply_many(recorded())
    before = text(state)
    garbage = [
        ("bms/p1/cell/1/state", b"{not json", 3.0),
        ("bms/p1/cell/1/state", b"[1, 2]", 3.0),
        ("bms/p1/cell/1/state", b"\xff\xfe", 3.0),
        ("bms/p1/availability", b"maybe", 3.0),
        ("bms/p1/cell/-1/state", b"{}", 3.0),
        ("bms/p1/cell/abc/state", b"{}", 3.0),
        ("bms/p1/something", b"{}", 3.0),
        ("other/p1/availability", b"online", 3.0),
        ("bms/p2/cell/0/state", cell_payload(0).encode(), 3.0),  # another pack: not shown
    ]
    for t, p, n in garbage:
        assert state.apply(t, p, n) is False
    c = state.counters
    assert (c.invalid_payload, c.unknown_topic, c.other_pack) == (4, 4, 1)
    assert set(state.packs) == {"p1"} and sorted(state.packs["p1"].cells) == [0, 1, 2, 3]
    assert state.packs["p1"].availability == "online"
    # a bad field is a missing value, not a crash
    assert state.apply("bms/p1/cell/1/state", json.dumps({"soc": "abc", "r0_ohm": None, "stale": 3}), 4.0)
    assert state.packs["p1"].cells[1].values["soc"] is None and c.invalid_fields == 2
    state.tick(2.0)
    assert "payload 4" in text(state) and before.splitlines()[0] != text(state).splitlines()[0]


def test_what_the_dashboard_skips_is_named_with_its_topic_and_why():
    """A retained payload of another schema (none of the keys this version reads: an older service's, or
    another program's) is skipped, not shown as a row of dashes, and the view names the topics it skipped
    and why; before, only counts were shown ("payload 1") and the old-schema cell was a row of '-'."""
    state = DashboardState()
    state.apply_many(recorded())
    assert state.apply("bms/p1/cell/7/state", json.dumps({"soc_pct": 55.0, "r0": 0.0012}), 3.0) is False
    assert state.apply("bms/p1/pack/state", b'{"soc_min": 0.5,', 3.0) is False
    assert state.apply("bms/p1/cell/1/state", json.dumps({"soc": "0.5", "t_s": 3.0}), 3.0) is True
    assert 7 not in state.packs["p1"].cells and state.counters.invalid_payload == 2
    out = " ".join(text(state, width=400).split())
    assert "bms/p1/cell/7/state: none of the keys of this version's payload" in out
    assert "bms/p1/pack/state: not JSON" in out
    assert "bms/p1/cell/1/state: 'soc' is not a number (\"0.5\")" in out


def test_many_cells_are_split_into_side_by_side_tables():
    state = DashboardState()
    for i in range(10):
        state.apply(f"bms/big/cell/{i}/state", cell_payload(i), 1.0)
    out = text(state, width=220, max_rows=4)
    header = next(line for line in out.splitlines() if "SOC %" in line)
    assert header.count("SOC %") == 3
    assert "no pack state yet" in out and "availability unknown" in out


def test_parse_broker():
    assert parse_broker("localhost") == ("localhost", 1883)
    assert parse_broker("10.0.0.2:1884") == ("10.0.0.2", 1884)
    assert parse_broker("[::1]:1885") == ("::1", 1885)
    for bad in (":1883", "host:x", "host:70000"):
        with pytest.raises(ValueError):
            parse_broker(bad)


def test_subscriber_against_mosquitto(mosquitto):
    async def scenario() -> DashboardState:
        state = DashboardState()
        stop = asyncio.Event()
        task = asyncio.create_task(run_dashboard(state, mosquitto.host, mosquitto.port, stop=stop, duration_s=20))
        await wait_until(lambda: state.connected, 5, "dashboard connected")
        async with aiomqtt.Client(mosquitto.host, mosquitto.port) as pub:
            for topic, payload, _ in recorded("car1"):
                await pub.publish(topic, payload, qos=1, retain=topic.endswith("availability"))
            await pub.publish("bms/car1/cell/9/state", b"garbage", qos=1)
            await wait_until(lambda: state.counters.messages >= 7, 5, "all messages")
        stop.set()
        await asyncio.wait_for(task, 5)
        return state

    state = run_async(scenario())
    assert state.status == "stopped" and not state.connected
    view = state.packs["car1"]
    assert view.availability == "online" and sorted(view.cells) == [0, 1, 2, 3]
    assert view.cells[1].values["r0_ohm"] == pytest.approx(0.020125)
    assert state.counters.invalid_payload == 1
    state.tick(time.monotonic())
    out = text(state)
    assert "pack car1" in out and "81.00" in out and "20.125" in out


def test_dashboard_command_prints_a_snapshot_when_piped(mosquitto, capsys):
    async def retain() -> None:
        async with aiomqtt.Client(mosquitto.host, mosquitto.port) as pub:
            await pub.publish("bms/car2/availability", b"offline", qos=1, retain=True)

    run_async(retain())
    rc = main(["dashboard", "--broker", f"{mosquitto.host}:{mosquitto.port}", "--pack", "car2", "--duration-s", "1"])
    out = capsys.readouterr().out
    assert rc == 0 and "pack car2" in out and "offline" in out


def test_subscriber_waits_for_a_broker_that_comes_later(tmp_path):
    if not mosquitto_available():
        pytest.skip(f"mosquitto broker not found at {MOSQUITTO}")
    broker = Broker(tmp_path)  # port reserved, not started yet

    async def scenario() -> DashboardState:
        state = DashboardState()
        stop = asyncio.Event()
        task = asyncio.create_task(run_dashboard(state, broker.host, broker.port, stop=stop, reconnect_min_s=0.1,
                                                 reconnect_max_s=0.2))
        await wait_until(lambda: "unreachable" in state.status, 5, "a failed connect")
        assert "broker unreachable" in text(state)
        await asyncio.to_thread(broker.start)
        await wait_until(lambda: state.connected, 10, "the dashboard to connect")
        stop.set()
        await asyncio.wait_for(task, 5)
        return state

    try:
        state = run_async(scenario())
    finally:
        broker.stop()
    assert state.status == "stopped"
