"""End to end: ``bms-estimator demo`` runs (encode -> replay -> service -> MQTT -> view), prints its
summary and writes its figure, with a Mosquitto it starts itself, with the embedded broker, and
with MQTT off. The runs are cut (``--duration-s``) to keep the suite short; the full demo is the
same code over the whole cycle."""

from __future__ import annotations

import json
import re

import pytest

from e2e_helpers import Broker, mosquitto_available, replay_through_service

from bms_estimator.cli.__main__ import main
from bms_estimator.core.identifier import IdentifierConfig

pytestmark = pytest.mark.slow


def _embedded_available() -> bool:
    from bms_estimator.demo.broker import embedded_available

    return embedded_available()


def _run_demo(tmp_path, capsys, broker: str, duration_s: int | None) -> tuple[str, dict]:
    """``bms-estimator demo`` over the first ``duration_s`` of the cycle (None: the README's
    command, the whole cycle); checks the summary, the figure and the JSON."""
    out_dir = tmp_path / "demo"
    cut = [] if duration_s is None else ["--duration-s", str(duration_s)]
    rc = main(["demo", "--output", str(out_dir), *cut, "--broker", broker])
    assert rc == 0
    text = capsys.readouterr().out
    png = out_dir / "pack.png"
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 50_000
    assert f"Figure: {png}" in text
    summary = json.loads((out_dir / "pack_summary.json").read_text())
    truth = json.loads((out_dir / "pack.truth.json").read_text())
    assert summary["samples"] == (duration_s or round(truth["duration_s"])) and summary["n_cells"] == 16 == len(truth["cells"])
    assert summary["decode_errors"] == 0 and summary["frames_decoded"] == summary["frames"]
    # the summary: a row per cell with the SOC error, the voltage RMSE and the parameters
    assert "Summary: 16-cell pack from lg-hg2 la92" in text
    rows = [line for line in text.splitlines() if re.match(r"^\s+\d+\*?\s+\d\.\d{3}\s+\d\.\d{3} \|", line)]
    assert len(rows) == 16, text
    for c in summary["cells"]:
        for key in ("soc_rmse_pct", "soc_error_end_pct", "voltage_osa_rmse_mv", "r0_ohm_final", "r1_ohm_final",
                    "tau1_s_final", "r2_ohm_final", "tau2_s_final", "c0_v_final", "capacity_ah_estimated"):
            assert isinstance(c[key], float), (key, c)
        assert 0.0 < c["r0_ohm_final"] < 0.1 and c["voltage_osa_rmse_mv"] < 30.0
    # state of power, energy and health at the end (issue 14), printed and in the JSON
    sox = summary["pack_sox_end"]
    assert sox["p_discharge_max_10s_w"] > 0 and sox["energy_left_wh"] > 0 and sox["energy_discharged_wh"] > 0
    m = re.search(r"10 s limits discharge\s+(\d+) W", text)
    assert m and float(m.group(1)) == pytest.approx(sox["p_discharge_max_10s_w"], abs=1.0)
    m = re.search(r"R0 ranking vs the injected spread: Spearman (-?\d\.\d{3})", text)
    assert m and float(m.group(1)) == pytest.approx(summary["spearman_r0_median_vs_injected"], abs=1e-3)
    # The R0 ranking builds over the first hour: the median R0 after the initialisation ranks the
    # injected spread at 0.90 after 1 h and 0.99 over the full run.  Before that the cells leave the
    # identifier's prior (20 mOhm here) one by one: at 15 min 2-3 of the 16 have, so a rank correlation
    # over the cells mostly ranks ties of the prior (it read 0.54 or 0.28 at 15 min, 0.19 at 20 min,
    # 0.83 at 25 min as that handful moved).  A short run checks what the identified cells do say.
    if summary["duration_s"] >= 3600:
        assert summary["spearman_r0_median_vs_injected"] >= 0.85
    prior_r0 = IdentifierConfig().prior_r0_ohm_ah / summary["capacity_ah_stated"]
    identified = [c for c in summary["cells"] if abs(c["r0_ohm_final"] - prior_r0) > 1e-6]
    assert identified, "no cell's R0 left the identifier's prior"
    # measured: 7-8 % below the injected median R0 at 15 min, within 1 % over the full run
    for c in identified:
        assert c["r0_ohm_final"] == pytest.approx(c["r0_ohm_true_median"], rel=0.2), c
    return text, summary


@pytest.mark.skipif(not mosquitto_available(), reason="mosquitto is not installed")
def test_demo_with_its_own_mosquitto(tmp_path, capsys):
    text, summary = _run_demo(tmp_path, capsys, "mosquitto", 1500)
    assert "MQTT: Mosquitto started by the demo at 127.0.0.1:" in text
    assert summary["mqtt_received"] > 100 and summary["mqtt_final_states_received"] == 16
    assert summary["mqtt_final_states_match_service"] is True
    assert "final states over MQTT = the service's: yes" in text


@pytest.mark.skipif(not _embedded_available(), reason="the embedded broker needs amqtt")
def test_demo_with_the_embedded_broker(tmp_path, capsys, record_property):
    """The README's command as on a fresh machine (no Mosquitto: the embedded broker), over the
    whole cycle. Its wall time is printed in the run's summary for CI's log (a figure, never
    asserted: the goal is under 60 s on an idle machine)."""
    text, summary = _run_demo(tmp_path, capsys, "embedded", None)
    assert "MQTT: embedded amqtt broker (pure Python" in text
    assert summary["mqtt_final_states_match_service"] is True
    # MQTT at the demo's mqtt.publish_period_s of log time per topic: 17 topics per period and the
    # finals (a state superseded in the publisher's latest-value buffer before it went out is not sent)
    from bms_estimator.demo.pipeline import MQTT_PUBLISH_PERIOD_S

    per_period = 17 * int(summary["samples"] // MQTT_PUBLISH_PERIOD_S)
    assert 0.9 * per_period <= summary["mqtt_received"] <= per_period + 2 * 17
    record_property("summary_line", f"[demo timing] bms-estimator demo --broker embedded, whole cycle "
                    f"({summary['samples']} s, {summary['frames']:,} frames): {summary['wall_s']:.1f} s wall, "
                    f"service {summary['replay_wall_s']:.1f} s ({summary['times_real_time']:.0f}x real time)")


def test_demo_without_mqtt(tmp_path, capsys):
    text, summary = _run_demo(tmp_path, capsys, "none", 900)
    assert "MQTT is disabled for this run" in text
    assert summary["mqtt_published"] == 0 and summary["mqtt_final_states_match_service"] is None


@pytest.mark.skipif(not mosquitto_available(), reason="mosquitto is not installed")
def test_demo_feed_equals_replay_over_a_bus(tmp_path):
    """The demo hands the frames to the service in process (``Service.feed``); the same frames
    written to a candump log and replayed over a python-can virtual bus into the service (the
    ``bms-estimator replay`` path, its states over MQTT) give the same SOC and parameters at
    every sample that arrived, bit for bit."""
    import asyncio
    import math

    from bms_estimator.demo.pipeline import prepare_pack, run_pipeline
    from bms_estimator.replay.encode_log import write_messages

    setup = prepare_pack("lg-hg2", None, 16, duration_s=300)
    log = tmp_path / "pack.log"
    write_messages(setup.frames.iter_messages(), log)
    broker = Broker(tmp_path / "broker").start()
    try:
        bus = asyncio.run(replay_through_service(log, n_cells=16, ocv_csv=setup.ocv_path,
                                                 capacity_ah=setup.capacity_stated_ah, speed=math.inf,
                                                 port=broker.port, state_dir=tmp_path))
    finally:
        broker.stop()
    demo = asyncio.run(run_pipeline(setup))
    rec = demo.record
    assert bus.decode_errors == 0 == demo.decode_errors and bus.samples >= 299
    row = {float(t): k for k, t in enumerate(rec.t_s)}
    compared = 0
    for j in range(16):
        for t_s, text in bus.cells[j].items():
            p = json.loads(text)
            k = row[float(t_s)]
            assert p["soc"] == rec.soc[k, j] and p["r0_ohm"] == rec.params["r0_ohm"][k, j], (j, t_s)
            assert p["r1_ohm"] == rec.params["r1_ohm"][k, j] and p["c0_v"] == rec.params["c0_v"][k, j], (j, t_s)
            compared += 1
    # at max speed the replay's publisher keeps the newest state per topic (older ones are
    # superseded while it sends; how many depends on the load); every cell's final state arrives,
    # and hundreds before it (352 with two other test runs loading this 2-core machine)
    assert compared >= 16 * 10 and all(bus.last_t_s in bus.cells[j] for j in range(16))
    # the demo's one extra closing frame completes one more sample than the log alone
    assert rec.rows == bus.samples + 1


@pytest.mark.skipif(not _embedded_available(), reason="the embedded broker needs amqtt")
def test_embedded_broker_is_a_child_process_that_ends_with_the_demo():
    """The embedded broker routes messages from a process of its own (not the demo's interpreter)
    and is gone when the demo's context ends."""
    import asyncio
    import os

    import aiomqtt

    from bms_estimator.demo.broker import open_broker

    async def roundtrip(host: str, port: int) -> bytes:
        async with aiomqtt.Client(host, port, identifier="embedded-test") as client:
            await client.subscribe("t/#", qos=1)
            await client.publish("t/x", b"hello", qos=1)
            async for message in client.messages:
                return bytes(message.payload)
        return b""

    with open_broker("embedded") as info:
        assert info.kind == "embedded"
        pid = int(re.search(r"process (\d+)", info.note).group(1))
        assert pid != os.getpid()
        os.kill(pid, 0)  # alive
        assert asyncio.run(asyncio.wait_for(roundtrip(info.host, info.port), 30)) == b"hello"
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_a_demo_shorter_than_the_initialisation_says_so_instead_of_nan(tmp_path, capsys):
    """`demo --duration-s 300` ended its summary with 'voltage OSA RMSE, mean over cells: nan mV'."""
    rc = main(["demo", "--output", str(tmp_path / "demo"), "--duration-s", "300", "--broker", "none", "--plain"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "voltage OSA RMSE, mean over cells: n/a (the run is not longer than the 600 s initialisation)" in text
    assert "nan" not in text.lower()


def test_a_demo_whose_broker_is_never_reached_fails_after_its_summary(tmp_path, capsys):
    """`demo --broker HOST:PORT` with nothing listening printed its summary and exited 0: the MQTT half of the
    demo had failed silently. Now the summary, then one error line, exit 1 (a broker failure)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here
    rc = main(["demo", "--output", str(tmp_path / "demo"), "--duration-s", "60", "--broker", f"127.0.0.1:{port}",
               "--plain"])
    assert rc == 1
    out, err = capsys.readouterr()
    assert "Summary: 16-cell pack" in out
    assert f"bms-estimator demo: error: MQTT broker 127.0.0.1:{port} never reached: nothing was published" in err
