"""The estimator daemon end to end: python-can ``virtual`` bus in-process, real Mosquitto.

Frames are built from a measured drive cycle (Panasonic 18650PF cycle_1, 1 s rows)
for a pack of 6 cells with small voltage offsets: per second of data, 10 pack
current frames (every 0.1 s, the first exactly on the second) and 10 rounds of
cell voltage frames, and one temperature frame. The reference is an offline
``SocEstimator`` fed the samples that the same decoder and sampler make of the
same frames; the service must match it bit for bit (CAN bytes, MQTT floats,
saved state).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from can.interfaces.virtual import VirtualBus
from structlog.testing import capture_logs

from bms_estimator.can.dbc import load_project_db
from bms_estimator.can.decoder import FrameDecoder
from bms_estimator.can.e2e import E2EStamper
from bms_estimator.can.encoder import StateEncoder
from bms_estimator.can.sampler import SampleAssembler
from bms_estimator.cli.__main__ import main as cli_main
from bms_estimator.core.ocv import OcvCurve
from bms_estimator.core.soc import SocEstimator
from bms_estimator.data import load_recording
from bms_estimator.ocv_table import read_ocv_table, read_ocv_tables, write_ocv_table
from bms_estimator.samples import drive_cycle, ocv_table
from bms_estimator.service.config import ConfigError, ServiceConfig, soc_config_from_core
from bms_estimator.service.daemon import Service, run_service
from bms_estimator.service.state import load_state, save_state
from tests.conftest import foxbms_dbc_path

from service_helpers import Collector, NotifySocket, free_port, retained, run_async, wait_until

REPO_ROOT = Path(__file__).resolve().parents[2]
DB = load_project_db()
N = 6
OFFSETS_V = np.array([0.0, 0.002, -0.0015, 0.001, -0.0005, 0.0025])
CAPACITY_AH = 2.9
T0 = 20_000.0  # frame time of row 0
PACK = "packT"

MSG = {name: DB.get_message_by_name(name) for name in (
    "PackMeasurement", "CellVoltages", "CellTemperatures",
    "CellStateA", "CellStateB", "PackSummary", "PackElectrical", "EstimatorStatus", "EstimatorCounters")}
CELL_STATE_IDS = {MSG["CellStateA"].frame_id, MSG["CellStateB"].frame_id}
PACK_IDS = {MSG["PackSummary"].frame_id, MSG["PackElectrical"].frame_id}
STATUS_IDS = {MSG["EstimatorStatus"].frame_id, MSG["EstimatorCounters"].frame_id}
OUTPUT_IDS = CELL_STATE_IDS | PACK_IDS | STATUS_IDS
PARAM_KEYS = ("r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "c0_v", "tau1_s", "tau2_s")


@functools.lru_cache(maxsize=1)
def cycle():
    return load_recording(drive_cycle("panasonic-18650pf", "cycle_1"))


@functools.lru_cache(maxsize=1)
def ocv() -> OcvCurve:
    return read_ocv_table(ocv_table("panasonic-18650pf"))


# ------------------------------------------------------------------ frames
STAMPER = E2EStamper(DB, "default")  # the sender side of the default mapping's end-to-end checks


def msg(name: str, values: dict[str, Any], t: float, *, scaling: bool = True) -> can.Message:
    """A frame as the BMS sends it: alive counter (next value unless ``values`` names it) and CRC."""
    m = MSG[name]
    return can.Message(timestamp=t, arbitration_id=m.frame_id, is_extended_id=m.is_extended_frame,
                       data=STAMPER.encode(name, values, scaling=scaling, strict=False))


def restamp(frames: list[can.Message]) -> list[can.Message]:
    """``frames`` as one sender sends them in this order: alive counters in list order, CRCs
    (for a test that inserts or replaces frames after building them)."""
    stamper = E2EStamper(DB, "default")
    return [can.Message(timestamp=f.timestamp, arbitration_id=f.arbitration_id, is_extended_id=f.is_extended_id,
                        data=stamper.stamp(f.arbitration_id, bytes(f.data))) for f in frames]


def current_frame(t: float, current_a: float, *, raw: int | None = None, invalid: bool = False) -> can.Message:
    if raw is not None:  # e.g. the NotAvailable raw value
        return msg("PackMeasurement", {"PackCurrent": raw, "PackVoltage": 24_000,
                                       "CurrentInvalid": 0, "VoltageInvalid": 0}, t, scaling=False)
    return msg("PackMeasurement", {"PackCurrent": current_a, "PackVoltage": 3.7 * N,
                                   "CurrentInvalid": int(invalid), "VoltageInvalid": 0}, t)


def voltage_frame(t: float, base: int, volts, *, raw: bool = False) -> can.Message:
    values = {"CellIndexBase": base, **{f"CellVoltage{j}": v for j, v in enumerate(volts)}}
    return msg("CellVoltages", values, t, scaling=not raw)


def row_frames(k: int, *, t_shift: float = 0.0, volts_override: dict[int, float] | None = None) -> list[can.Message]:
    """One second of bus traffic for drive-cycle row ``k`` (frame time T0 + k + t_shift)."""
    rec = cycle()
    i_a = float(rec.current_a[k])
    v = float(rec.voltage_v[k]) + OFFSETS_V
    if volts_override:
        v = v.copy()
        for cell, value in volts_override.items():
            v[cell] = value
    t_row = T0 + k + t_shift
    out = []
    for j in range(10):
        t = t_row + j * 0.1
        out.append(current_frame(t, i_a))
        for b, base in enumerate(range(0, N, 3)):
            out.append(voltage_frame(t + 0.002 + 0.001 * b, base, v[base:base + 3]))
    out.append(msg("CellTemperatures", {"CellIndexBase": 0, **{f"CellTemperature{j}": 25.0 + j for j in range(6)}},
                   t_row + 0.05))
    out.sort(key=lambda m: m.timestamp)  # stable: same-time frames keep their order
    return out


def rows(first: int, n: int, *, t_shift: float = 0.0, close: bool = True) -> list[can.Message]:
    """Rows ``first .. first+n-1`` plus (``close``) the next row's first current frame,
    which completes the last sample: ``n`` samples, t_s = T0 + first + 1 .. T0 + first + n."""
    out: list[can.Message] = []
    for k in range(first, first + n):
        out += row_frames(k, t_shift=t_shift)
    if close:
        out.append(current_frame(T0 + first + n + t_shift, float(cycle().current_a[first + n])))
    return out


@functools.lru_cache(maxsize=4)
def cached_rows(first: int, n: int) -> tuple[can.Message, ...]:
    return tuple(rows(first, n))


# --------------------------------------------------------------- reference
@dataclass
class Step:
    t_s: float
    sample: Any
    soc: np.ndarray
    params: dict[str, np.ndarray]
    frames: list[tuple[int, bytes]]  # CellStateA/B, PackSummary, PackElectrical


class Offline:
    """The same decoder, sampler and estimator as the service, fed directly."""

    def __init__(self, core: dict | None = None, estimator: SocEstimator | None = None) -> None:
        self.dec = FrameDecoder(DB, "default", N)
        self.smp = SampleAssembler(N, 1.0, 2.5)
        self.est = estimator or SocEstimator(N, ocv(), CAPACITY_AH, 1.0, config=soc_config_from_core(core or {}))
        self.enc = StateEncoder(DB)
        self.steps: list[Step] = []

    def feed(self, frames) -> Offline:
        est = self.est
        last_t = None
        fed = False
        for m in frames:
            for s in self.smp.feed_frame(self.dec.decode(m), m.timestamp):
                if last_t is not None and s.t_s - s.period_s - last_t > 0.5 * s.period_s:  # a time jump: parked
                    est.rest(s.t_s - s.period_s - last_t)
                last_t = s.t_s
                # from the first valid current on, every sample; a lost current is NaN (held by the estimator)
                known = s.current_valid and math.isfinite(s.current_a)
                fed = fed or known
                if fed:
                    est.update(s.current_a if known else math.nan, s.cell_voltage_v, s.valid,
                               temperature_c=s.cell_temperature_c)
                p = {k: v.copy() for k, v in est.params.items()}
                fr = self.enc.encode_cells(np.arange(N), est.soc, p["r0_ohm"], p["r1_ohm"], p["c1_f"], p["r2_ohm"],
                                           p["c2_f"], p["c0_v"])
                fr += self.enc.encode_pack_summary(est.soc, s.current_a, s.pack_voltage_v,
                                                   cells_valid=int(np.count_nonzero(s.valid)))
                self.steps.append(Step(s.t_s, s, est.soc.copy(), p, [(f.arbitration_id, bytes(f.data)) for f in fr]))
        return self

    def by_t(self) -> dict[float, Step]:
        return {s.t_s: s for s in self.steps}


# ------------------------------------------------------------------ service
def deep_merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def config_data(tmp_path: Path, channel: str, *, mqtt_port: int | None = None, **over: Any) -> dict:
    data = {
        "pack": {"pack_id": PACK, "n_cells": N, "capacity_ah": CAPACITY_AH,
                 "ocv_csv": str(ocv_table("panasonic-18650pf"))},
        "can": {"interface": "virtual", "channel": channel,
                "bus": {"reopen_initial_s": 0.01, "reopen_max_s": 0.05}},
        "estimator": {"sample_period_s": 1.0, "staleness_s": 2.5},
        "mqtt": {"enabled": mqtt_port is not None, "host": "127.0.0.1", "port": mqtt_port or 1883,
                 "reconnect_min_s": 0.05, "reconnect_max_s": 0.2, "timeout_s": 3.0},
        "state": {"path": str(tmp_path / "state.npz"), "save_interval_s": 60.0},
        "health": {"port": 0},
        "logging": {"level": "INFO"},
    }
    return deep_merge(data, over)


def make_cfg(tmp_path: Path, channel: str, **kw: Any) -> ServiceConfig:
    return ServiceConfig(**config_data(tmp_path, channel, **kw))


def channel() -> str:
    return f"bmsd-{uuid.uuid4().hex[:8]}"


class VBus:
    """The rest of the vehicle: a feeder node and a listener node on the service's virtual channel."""

    def __init__(self, ch: str) -> None:
        self.tx = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
        self.rx = can.Bus(interface="virtual", channel=ch)
        self.outputs: list[can.Message] = []

    def send(self, frames) -> None:
        for f in frames:
            self.tx.send(f)

    def collect(self) -> list[can.Message]:
        while (m := self.rx.recv(0)) is not None:
            if m.arbitration_id in OUTPUT_IDS:
                self.outputs.append(m)
        return self.outputs

    def of(self, ids) -> list[can.Message]:
        return [m for m in self.collect() if m.arbitration_id in ids]

    async def wait_outputs(self, ids, n: int, timeout: float = 10.0) -> list[can.Message]:
        await wait_until(lambda: len(self.of(ids)) >= n, timeout, f"{n} output frames")
        return self.of(ids)

    def shutdown(self) -> None:
        self.tx.shutdown()
        self.rx.shutdown()


@contextlib.asynccontextmanager
async def running(cfg: ServiceConfig, *, bus_factory=None, wait_ready: bool = True):
    svc = Service(cfg, bus_factory=bus_factory)
    stop = asyncio.Event()
    task = asyncio.create_task(svc.run(stop))
    try:
        if wait_ready:
            await wait_until(lambda: svc.ready.is_set() or task.done(), 10, "service ready")
            assert not task.done(), task.exception()
        yield svc
    finally:
        stop.set()
        await asyncio.wait_for(task, 20)


async def wait_samples(svc: Service, n: int, timeout: float = 15.0) -> None:
    await wait_until(lambda: svc.pipeline.counters.samples >= n, timeout, f"{n} samples (have {svc.pipeline.counters.samples})")


async def http_get(port: int, path: str) -> tuple[int, str]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
    await writer.drain()
    data = await asyncio.wait_for(reader.read(), 5)
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body.decode()


async def scrape(svc: Service) -> dict[str, float]:
    """/metrics through prometheus_client's parser: ``name`` for a series without labels,
    ``name{label="value"}`` for one with, and ``name`` = the sum over the labels of a counter."""
    from prometheus_client.parser import text_string_to_metric_families

    status, body = await http_get(svc.health_port, "/metrics")
    assert status == 200
    out: dict[str, float] = {}
    for family in text_string_to_metric_families(body):
        for s in family.samples:
            if s.labels:
                labels = ",".join(f'{k}="{v}"' for k, v in sorted(s.labels.items()))
                out[f"{s.name}{{{labels}}}"] = s.value
                if family.type == "counter":
                    out[s.name] = out.get(s.name, 0.0) + s.value
            else:
                out[s.name] = s.value
    return out


def assert_state_file_valid(path: Path, *, soc: np.ndarray | None = None) -> dict:
    st = load_state(path, pack_id=PACK, n_cells=N, max_age_s=None)
    assert st is not None, f"state file {path} not usable"
    assert st.meta["fingerprint"]
    if soc is not None:
        np.testing.assert_array_equal(st["soc"], soc)
    return st


def run_bad_input(tmp_path: Path, frames: list[can.Message], n_samples: int, *, expect_equal: bool = True,
                  **cfg_over: Any) -> tuple[dict[str, float], Offline, Service]:
    """Feed ``frames`` to a service; return /metrics, the offline reference of the same frames, the service."""
    ch = channel()
    cfg = make_cfg(tmp_path, ch, **cfg_over)
    ref = Offline().feed(frames)
    assert len(ref.steps) == n_samples

    async def main():
        vb = VBus(ch)
        try:
            async with running(cfg) as svc:
                vb.send(frames)
                await wait_samples(svc, n_samples)
                await vb.wait_outputs(CELL_STATE_IDS, 2 * N * n_samples)
                metrics = await scrape(svc)
                if expect_equal:
                    got = [(m.arbitration_id, bytes(m.data)) for m in vb.of(CELL_STATE_IDS | PACK_IDS)]
                    assert got == [f for s in ref.steps for f in s.frames]
                    np.testing.assert_array_equal(svc.estimator.soc, ref.est.soc)
                final_soc = svc.estimator.soc.copy()
        finally:
            vb.shutdown()
        return metrics, svc, final_soc

    metrics, svc, final_soc = run_async(main(), 40)
    assert svc.pipeline.counters.tick_errors == 0
    assert np.isfinite(final_soc).all()
    assert_state_file_valid(Path(cfg.state.path), soc=final_soc)
    return metrics, ref, svc


# ================================================================== the tests
def test_service_matches_offline_estimator_on_can_and_mqtt(mosquitto, tmp_path):
    n_rows = 300
    frames = list(cached_rows(0, n_rows))
    # the paper's c0 method: its compensation is a visible SOC jump to check below (the EKF's
    # corrections are small steps every sample; the equivalence holds for both)
    core = {"soc_method": "c0"}
    ref = Offline(core).feed(frames)
    assert len(ref.steps) == n_rows
    # the frames carry the measured data: the samples are the drive-cycle rows (DBC resolution)
    rec = cycle()
    for k, step in enumerate(ref.steps):
        assert step.t_s == T0 + k + 1
        assert abs(step.sample.current_a - rec.current_a[k]) <= 0.6e-3
        np.testing.assert_allclose(step.sample.cell_voltage_v, rec.voltage_v[k] + OFFSETS_V, atol=0.6e-4)
        assert step.sample.valid.all() and step.sample.current_valid
    # a working estimator: starts from the OCV (the file starts at full, not yet relaxed, so
    # the OCV reads low), coulomb-counts down, and its first c0 compensation moves the SOC
    # towards the truth (counting from the known full start) within these 5 minutes
    soc0, soc_end = ref.steps[0].soc, ref.steps[-1].soc
    assert np.all((soc0 > 0.8) & (soc0 < 0.97))
    counted = -np.sum(rec.current_a[1:n_rows]) / 3600 / CAPACITY_AH
    socs = np.array([s.soc for s in ref.steps])
    jump = np.flatnonzero(np.any(np.diff(socs, axis=0) > 0.01, axis=1))
    first = int(jump[0]) if jump.size else n_rows - 1
    np.testing.assert_allclose(soc0 - socs[first], -np.sum(rec.current_a[1:first + 1]) / 3600 / CAPACITY_AH,
                               atol=0.01)
    assert np.all(ref.est.corrections >= 1)
    truth_end = 1.0 - counted
    assert np.all(np.abs(soc_end - truth_end) < 0.5 * np.abs(soc0 - 1.0)), (soc_end, truth_end)
    assert np.ptp(soc0) > 0  # the cell offsets show

    ch = channel()
    cfg = make_cfg(tmp_path, ch, mqtt_port=mosquitto.port, estimator={"core": core})
    root = f"bms/{PACK}"

    async def main():
        vb = VBus(ch)
        try:
            async with Collector(mosquitto.port, (f"{root}/#", "homeassistant/#")) as col:
                async with running(cfg) as svc:
                    await col.wait(lambda c: "online" in c.payloads(f"{root}/availability"), 10, "online")
                    vb.send(frames)
                    await wait_samples(svc, n_rows)
                    got = await vb.wait_outputs(CELL_STATE_IDS | PACK_IDS, (2 * N + 2) * n_rows)
                    status = await vb.wait_outputs(STATUS_IDS, 2 * n_rows)
                    t_last = T0 + n_rows
                    await col.wait(lambda c: all(
                        any(json.loads(p)["t_s"] == t_last for p in c.payloads(f"{root}/cell/{i}/state"))
                        for i in range(N)), 10, "the last cell states")
                    metrics = await scrape(svc)
                    health = await http_get(svc.health_port, "/healthz")
                    final_soc = svc.estimator.soc.copy()
                await col.wait(lambda c: c.payloads(f"{root}/availability")[-1:] == ["offline"], 5, "offline")
                return got, status, metrics, health, final_soc, list(col.messages)
        finally:
            vb.shutdown()

    got, status, metrics, health, final_soc, messages = run_async(main(), 60)

    # CAN: every sample's CellStateA/B + PackSummary/PackElectrical, byte-identical to the offline run
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [f for s in ref.steps for f in s.frames]
    soc_raw = [MSG["CellStateA"].decode(m.data) for m in got if m.arbitration_id == MSG["CellStateA"].frame_id]
    last = {d["CellIndex"]: d for d in soc_raw[-N:]}
    np.testing.assert_allclose([last[i]["Soc"] / 100 for i in range(N)], ref.est.soc, atol=0.000125 + 1e-12)
    st = [MSG["EstimatorStatus"].decode(m.data) for m in status if m.arbitration_id == MSG["EstimatorStatus"].frame_id]
    co = [MSG["EstimatorCounters"].decode(m.data, decode_choices=False)
          for m in status if m.arbitration_id == MSG["EstimatorCounters"].frame_id]
    assert max(d["Samples"] for d in st) == n_rows
    assert all(d["DecodeErrors"] == 0 and d["Rejections"] == 0 for d in co)
    assert sum(d["EstimatorState"] == 1 and d["StaleCells"] == 0 for d in co) == n_rows  # running, all cells fresh
    np.testing.assert_array_equal(final_soc, ref.est.soc)

    # MQTT: each cell state equals the offline estimate of its sample, to the last bit
    by_t = ref.by_t()
    cell_msgs = 0
    for m in messages:
        topic = m.topic.value
        if topic.startswith(f"{root}/cell/"):
            i = int(topic.split("/")[3])
            p = json.loads(bytes(m.payload))
            step = by_t[p["t_s"]]
            assert p["soc"] == step.soc[i]
            for key in PARAM_KEYS:
                assert p[key] == step.params[key][i], key
            assert p["stale"] is False and p["temperature_c"] == 25.0 + i
            cell_msgs += 1
    assert cell_msgs >= N
    pack = [json.loads(bytes(m.payload)) for m in messages if m.topic.value == f"{root}/pack/state"]
    assert pack and pack[-1]["t_s"] == T0 + n_rows and pack[-1]["soc_mean"] == pytest.approx(ref.est.soc.mean())
    assert pack[-1]["cells_stale"] == 0 and pack[-1]["cells_valid"] == N
    # state of power, energy and health (issue 14) in the pack payload and the metrics
    assert pack[-1]["p_discharge_max_10s_w"] > 0 and pack[-1]["i_charge_max_2s_a"] >= 0
    assert pack[-1]["energy_left_wh"] > 0 and pack[-1]["energy_discharged_wh"] > 0
    assert metrics['bms_pack_power_limit_watts{direction="discharge",horizon="10s"}'] == pytest.approx(
        pack[-1]["p_discharge_max_10s_w"])
    assert metrics["bms_pack_energy_left_wh"] == pytest.approx(pack[-1]["energy_left_wh"])
    # availability and Home Assistant discovery (retained)
    avail = [bytes(m.payload).decode() for m in messages if m.topic.value == f"{root}/availability"]
    assert avail[0] == "online" and avail[-1] == "offline"
    disco = {m.topic.value: json.loads(bytes(m.payload)) for m in messages if m.topic.value.startswith("homeassistant/")}
    for i in range(N):
        c = disco[f"homeassistant/sensor/bms_{PACK}_cell{i}_soc/config"]
        assert c["state_topic"] == f"{root}/cell/{i}/state" and c["enabled_by_default"] is False
        # unavailable while the service is offline or the cell is stale
        assert {"topic": f"{root}/availability"} in c["availability"] and c["availability_mode"] == "all"
        assert any(a["topic"] == c["state_topic"] and "stale" in a["value_template"] for a in c["availability"])
    assert f"homeassistant/sensor/bms_{PACK}_pack_soc_mean/config" in disco

    # health and metrics while it ran
    assert health[0] == 200
    assert metrics["bms_samples_total"] == n_rows
    assert metrics["bms_can_frames_decoded_total"] == len(frames)
    assert metrics["bms_decode_problems_total"] == 0
    assert metrics["bms_mqtt_published_total"] > N
    assert metrics["bms_can_tx_frames_total"] >= (2 * N + 4) * n_rows
    assert metrics["bms_healthy"] == 1
    ident = ref.est.identifier  # the estimator's own counters, as the offline run has them
    assert metrics["bms_estimator_rejections_total"] == int(ident.rejections.sum())
    assert metrics["bms_estimator_restarts_total"] == int(ident.restarts.sum())
    assert metrics["bms_estimator_corrections_total"] == int(ref.est.corrections.sum())
    # and the state saved at shutdown is the final estimate
    assert_state_file_valid(Path(cfg.state.path), soc=ref.est.soc)


def test_ocv_tables_at_several_temperatures_are_read_at_each_cells_temperature(tmp_path):
    """pack.ocv_csv takes a list of tables; the estimator reads them at each cell's temperature from CAN
    (25-30 degC here), and every cell's SOC uncertainty leaves the service with its state."""
    warm = ocv()
    cold = OcvCurve(warm.soc, warm.ocv_v + 0.02, warm.hysteresis_v, temperature_c=0.0,
                    capacity_discharge_ah=2.6)
    paths = [str(write_ocv_table(warm, tmp_path / "warm.csv")) if warm.temperature_c is not None else None,
             str(write_ocv_table(cold, tmp_path / "cold.csv"))]
    assert paths[0] is not None, "the shipped table carries its temperature"
    frames = rows(0, 30)
    metrics, _, svc = run_bad_input(tmp_path, frames, 30, expect_equal=False, pack={"ocv_csv": paths})
    est = svc.estimator
    assert list(est.ocv.temperatures_c) == [0.0, warm.temperature_c]
    np.testing.assert_array_equal(est.temperature_c, 25.0 + np.arange(N))  # CellTemperature0..5 of row_frames
    # the same frames offline with the same tables and temperatures give the same SOC
    offline = Offline(estimator=SocEstimator(N, read_ocv_tables(paths), CAPACITY_AH, 1.0)).feed(frames)
    np.testing.assert_array_equal(est.soc, offline.est.soc)
    snap = svc.pipeline.last
    sigma = np.asarray(snap.cells["soc_sigma"])
    assert sigma.shape == (N,) and np.all((sigma > 0) & (sigma < 0.2))
    bad = config_data(tmp_path, channel(), pack={"ocv_csv": [paths[0], str(tmp_path / "missing.csv")]})
    with pytest.raises(ConfigError, match="pack.ocv_csv"):  # a path to no file is the configuration's mistake
        Service(ServiceConfig(**bad))
    bad = config_data(tmp_path, channel(), pack={"ocv_csv": [paths[0], str(tmp_path / "cold.csv" / "x.csv")]})
    with pytest.raises(ConfigError, match=r"pack.ocv_csv: .*cold.csv/x.csv: not a directory"):
        Service(ServiceConfig(**bad))
    # a table of another cell (the LG HG2 sample's, labelled 20 degC, beside the Panasonic one): each file is fine,
    # the list doubtful: the service starts and says so in one warning naming both files (core.ocv_surface, item 9)
    other = read_ocv_table(ocv_table("lg-hg2"))
    other_path = str(write_ocv_table(OcvCurve(other.soc, other.ocv_v, temperature_c=20.0), tmp_path / "other20.csv"))
    mixed = config_data(tmp_path, channel(), pack={"ocv_csv": [paths[0], other_path]})
    with capture_logs() as logs:
        Service(ServiceConfig(**mixed))
    said = [e for e in logs if e.get("config_key") == "pack.ocv_csv" and e["log_level"] == "warning"]
    assert len(said) == 1, logs
    assert re.search(r"other20.csv \(20 degC\) and .*warm.csv .* differ by \d+ mV RMS .*tables of one cell\?",
                     said[0]["event"]), said
    with capture_logs() as logs:  # the two tables of one cell: nothing said
        Service(ServiceConfig(**config_data(tmp_path, channel(), pack={"ocv_csv": paths})))
    assert not [e for e in logs if e.get("config_key") == "pack.ocv_csv"], logs


def test_the_priors_take_the_cells_temperature_from_can_when_it_comes(tmp_path):
    """The cells' temperature frames come after the first samples (slower or multiplexed frames on a real
    bus; here 3 s late), at 0 degC: the identifier's prior resistances and the EKF's diffusion resistance
    start at 0 degC (x2.16 of the 25 degC prior), as with the temperature there from the first sample. They
    were taken from the first sample alone: with no temperature there, at 25 degC for the whole drive."""
    cold = {"CellIndexBase": 0, **{f"CellTemperature{j}": 0.0 for j in range(N)}}

    def frames(late_s: float) -> list:
        out = [m for m in rows(0, 30) if m.arbitration_id != MSG["CellTemperatures"].frame_id]
        out += [msg("CellTemperatures", cold, T0 + k + 0.05) for k in range(30) if k >= late_s]
        out.sort(key=lambda m: m.timestamp)
        return restamp(out)

    at = {}
    for late_s in (0.0, 3.0):
        _, ref, svc = run_bad_input(tmp_path / f"late{late_s:g}", frames(late_s), 30)
        est = svc.estimator
        assert not est.identifier.identified.any()  # still on the prior after 30 s
        np.testing.assert_array_equal(est.temperature_c, 0.0)
        at[late_s] = (est.identifier.params.r0_ohm.copy(), est.ekf.r_diffusion_ohm.copy())
    prior_25 = SocEstimator(N, ocv(), CAPACITY_AH, 1.0)
    f0 = np.exp(2500.0 * (1 / 273.15 - 1 / 298.15))
    np.testing.assert_allclose(at[3.0][0], prior_25.identifier.params.r0_ohm * f0, rtol=1e-9)
    np.testing.assert_allclose(at[3.0][0], at[0.0][0], rtol=1e-9)
    np.testing.assert_allclose(at[3.0][1], at[0.0][1], rtol=0.02)  # r_d: 3 s of drive learnt less
    assert np.all(at[3.0][1] > 1.8 * prior_25.ekf.r_diffusion_ohm)


def test_unknown_ids_are_ignored_and_counted(tmp_path):
    clean = rows(0, 30)
    frames = []
    for k, f in enumerate(clean):
        frames.append(f)
        if k % 10 == 0:  # between the real ones: a standard id, an extended id, an id of another DBC message
            frames.append(can.Message(timestamp=f.timestamp, arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
            frames.append(can.Message(timestamp=f.timestamp, arbitration_id=0x1ABCDEF, data=bytes(8)))
    n_unknown = len(frames) - len(clean)
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    metrics, ref, _ = run_bad_input(tmp_path / "a", frames, 30, can={"kernel_filters": False})
    assert metrics['bms_can_frames_ignored_total{reason="unknown_id"}'] == n_unknown
    assert metrics["bms_decode_problems_total"] == 0
    # no effect at all: the same estimate as the clean stream
    np.testing.assert_array_equal(ref.est.soc, Offline().feed(clean).est.soc)

    # by default the bus is filtered down to the mapped ids (by the kernel on socketcan):
    # the other frames never reach the decoder
    metrics, ref, svc = run_bad_input(tmp_path / "b", frames, 30)
    assert metrics["bms_can_frames_received_total"] == len(clean)
    assert metrics['bms_can_frames_ignored_total{reason="unknown_id"}'] == 0
    mapped = {(MSG[name].frame_id, True) for name in ("PackMeasurement", "CellVoltages", "CellTemperatures")}
    filters = {(f["can_id"], f["extended"]) for f in svc.bus_cfg.can_filters}
    assert mapped <= filters and (0x123, False) not in filters
    assert all(f["can_mask"] == 0x1FFFFFFF for f in svc.bus_cfg.can_filters if f["extended"])


def test_short_frames_are_counted(tmp_path):
    clean = rows(0, 30)
    frames = []
    for f in clean:
        frames.append(f)
        if f.arbitration_id == MSG["CellVoltages"].frame_id and f.data[0] == 3:
            frames.append(can.Message(timestamp=f.timestamp, arbitration_id=f.arbitration_id,
                                      is_extended_id=True, data=bytes(f.data[:5])))
    n_short = len(frames) - len(clean)
    metrics, ref, _ = run_bad_input(tmp_path, frames, 30)
    assert metrics['bms_decode_problems_total{reason="short_frame"}'] == n_short
    assert metrics["bms_decode_problems_total"] == n_short
    np.testing.assert_array_equal(ref.est.soc, Offline().feed(clean).est.soc)


def test_undecodable_and_unmapped_mux_values_are_counted(tmp_path):
    clean = rows(0, 30)
    frames = list(clean)
    t = T0 + 10.05
    bad = bytearray(voltage_frame(t, 0, [3.9, 3.9, 3.9]).data)
    bad[0:2] = (2500).to_bytes(2, "little")  # the DBC defines CellIndexBase 0..1999
    frames.append(can.Message(timestamp=t, arbitration_id=MSG["CellVoltages"].frame_id, data=bytes(bad)))
    frames.append(voltage_frame(t, 1500, [3.9, 3.9, 3.9]))  # legal, but no cell of this pack
    frames.sort(key=lambda m: m.timestamp)
    metrics, ref, _ = run_bad_input(tmp_path, frames, 30)
    assert metrics['bms_decode_problems_total{reason="bad_mux"}'] == 1
    assert metrics['bms_can_frames_ignored_total{reason="unmapped"}'] == 1
    np.testing.assert_array_equal(ref.est.soc, Offline().feed(clean).est.soc)


def test_spoofed_frames_and_a_lost_frame_are_dropped_by_the_default_end_to_end_checks(tmp_path):
    """The shipped default mapping checks the project DBC's CRC and alive counters. Injected
    PackMeasurement frames with an in-range +-5000 A current and a wrong CRC (the counter value the
    sender sends next, as a spoofer would guess it) are dropped, counted, and leave the estimate
    bit-identical to the clean run; a current frame lost on the bus makes the next one skip a value,
    which is dropped and counted too."""
    clean = rows(0, 30)
    frames = list(clean)
    cur = [k for k, f in enumerate(clean) if f.arbitration_id == MSG["PackMeasurement"].frame_id]
    spoofs = []
    for n, k in enumerate(cur[20:200:45]):  # four spoofs, +5000 and -5000 A in turn
        real = clean[cur[cur.index(k) + 1]]  # the sender's next current frame: its counter value
        d = MSG["PackMeasurement"].decode(real.data, decode_choices=False)
        d.update(PackCurrent=5000.0 if n % 2 == 0 else -5000.0, MeasurementCrc=real.data[7] ^ 0x3C)
        spoofs.append(msg("PackMeasurement", d, clean[k].timestamp + 0.001))
    frames += spoofs
    frames.sort(key=lambda m: m.timestamp)  # stable: each spoof right after its real frame
    metrics, ref, _ = run_bad_input(tmp_path, frames, 30)
    assert metrics['bms_decode_problems_total{reason="e2e_crc"}'] == len(spoofs) == 4
    assert metrics['bms_decode_problems_total{reason="e2e_counter"}'] == 0
    np.testing.assert_array_equal(ref.est.soc, Offline().feed(clean).est.soc)  # the spoofs reached nothing

    lost = [f for k, f in enumerate(clean) if k != cur[57]]  # one current frame never arrives
    metrics, ref, _ = run_bad_input(tmp_path / "lost", lost, 30)
    assert metrics['bms_decode_problems_total{reason="e2e_counter"}'] == 1
    assert metrics['bms_decode_problems_total{reason="e2e_crc"}'] == 0
    assert metrics["bms_decode_problems_total"] == 1


def test_not_available_out_of_range_and_invalid_values(tmp_path):
    frames: list[can.Message] = []
    for k in range(40):
        if k in (10, 11):  # two seconds without a usable current: NotAvailable, then flagged invalid
            for f in row_frames(k):
                if f.arbitration_id == MSG["PackMeasurement"].frame_id:
                    f = current_frame(f.timestamp, 0.0, raw=-(2**23)) if k == 10 else current_frame(f.timestamp, 1.0, invalid=True)
                frames.append(f)
        elif 20 <= k < 26:  # cell 4 reads 6 V (above valid_max 5.5 V), cell 1 NotAvailable
            for f in row_frames(k, volts_override={4: 6.0}):
                if f.arbitration_id == MSG["CellVoltages"].frame_id and f.data[0] == 0:
                    d = MSG["CellVoltages"].decode(f.data, decode_choices=False, scaling=False)
                    d["CellVoltage1"] = 0xFFFF
                    f = msg("CellVoltages", d, f.timestamp, scaling=False)
                frames.append(f)
        else:
            frames += row_frames(k)
    frames.append(current_frame(T0 + 40, float(cycle().current_a[40])))
    metrics, ref, svc = run_bad_input(tmp_path, restamp(frames), 40)
    assert metrics['bms_decode_problems_total{reason="not_available"}'] == 10 + 60
    assert metrics['bms_decode_problems_total{reason="flagged_invalid"}'] == 10
    assert metrics['bms_decode_problems_total{reason="out_of_range"}'] == 60
    # the samples of rows 10 and 11 have no current: counted with its running mean, and counted here
    assert metrics["bms_samples_current_invalid_total"] == 2
    # cells 1 and 4 went stale while they sent nothing usable (staleness 2.5 s)
    stale = [s for s in ref.steps if s.sample.current_valid and not s.sample.valid.all()]
    assert len(stale) == 4 and all(not s.sample.valid[1] and not s.sample.valid[4] for s in stale)
    assert all(s.sample.valid[[0, 2, 3, 5]].all() for s in stale)
    assert np.isfinite(ref.est.soc).all()


def test_gaps_backward_and_rewound_time(tmp_path):
    frames = rows(0, 20, close=False)
    frames += rows(20, 20, t_shift=100.0, close=False)  # 100 s of silence: grid re-anchored
    at = len(frames) - 150
    frames.insert(at, current_frame(frames[at - 1].timestamp - 1.0, 5.0))  # 1 s in the past: ignored
    frames += rows(40, 20, t_shift=-5000.0)  # a new log from an older time: sampler reset
    frames = restamp(frames)
    metrics, ref, _ = run_bad_input(tmp_path, frames, len(Offline().feed(frames).steps))
    assert metrics['bms_sample_anomalies_total{kind="time_jump"}'] == 1
    assert metrics['bms_sample_anomalies_total{kind="backward_frame"}'] == 1
    assert metrics['bms_sample_anomalies_total{kind="rewind"}'] == 1
    assert metrics["bms_samples_total"] >= 55


class FlakyBus(VirtualBus):
    """A virtual bus that dies like an unplugged adapter after ``fail_after`` frames."""

    def __init__(self, *a: Any, fail_after: int, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self._left = fail_after

    def _recv_internal(self, timeout):
        m, filtered = super()._recv_internal(timeout)
        if m is not None:
            self._left -= 1
            if self._left < 0:
                raise can.CanOperationError("adapter unplugged", error_code=errno.ENODEV)
        return m, filtered


def test_bus_errors_and_a_bus_that_goes_away_and_returns(tmp_path):
    ch = channel()
    cfg = make_cfg(tmp_path, ch)
    calls = {"n": 0}

    def factory(bcfg):
        calls["n"] += 1
        if calls["n"] <= 2:
            raise OSError(errno.ENODEV, "No such device")  # not plugged in yet
        if calls["n"] == 3:
            return FlakyBus(channel=bcfg.channel, fail_after=20 * 31)  # dies after ~20 s of traffic
        return VirtualBus(channel=bcfg.channel)

    async def main():
        vb = VBus(ch)
        stop_feed = asyncio.Event()

        async def feed():
            k = 0
            while not stop_feed.is_set() and k < 2000:
                vb.send(row_frames(k))
                vb.tx.send(can.Message(is_error_frame=True, timestamp=T0 + k + 0.95, arbitration_id=0, data=bytes(8)))
                k += 1
                await asyncio.sleep(0.005)

        feeder = None
        try:
            async with running(cfg, bus_factory=factory) as svc:
                assert calls["n"] == 3  # ready only once the bus was open
                feeder = asyncio.create_task(feed())
                await wait_until(lambda: svc.pipeline.counters.samples >= 10, 10, "samples before the failure")
                await wait_until(lambda: svc.bus.counters.bus_errors >= 1, 10, "the bus failure")
                after = svc.pipeline.counters.samples
                await wait_until(lambda: svc.pipeline.counters.samples >= after + 20, 10, "samples after the reopen")
                stop_feed.set()
                await feeder
                metrics = await scrape(svc)
                soc = svc.estimator.soc.copy()
        finally:
            stop_feed.set()
            vb.shutdown()
        return metrics, soc

    metrics, soc = run_async(main(), 40)
    assert metrics['bms_can_bus_events_total{event="open_failure"}'] == 2
    assert metrics['bms_can_bus_events_total{event="error"}'] >= 1
    assert metrics['bms_can_bus_events_total{event="open"}'] >= 2
    assert metrics["bms_tick_errors_total"] == 0
    assert np.isfinite(soc).all()
    assert_state_file_valid(Path(cfg.state.path), soc=soc)


def test_broker_down_at_start_then_up(broker_factory, tmp_path):
    port = free_port()
    ch = channel()
    cfg = make_cfg(tmp_path, ch, mqtt_port=port)
    root = f"bms/{PACK}"

    async def main():
        vb = VBus(ch)
        try:
            async with running(cfg) as svc:
                vb.send(rows(0, 20))
                await wait_samples(svc, 20)
                # CAN output does not wait for the broker
                await vb.wait_outputs(CELL_STATE_IDS, 2 * N * 20)
                await wait_until(lambda: svc.publisher.counters.connect_failures >= 1, 5, "connect failures")
                assert svc.publisher.counters.published == 0
                broker = broker_factory(port=port)
                async with Collector(port, (f"{root}/#",)) as col:
                    await wait_until(lambda: svc.publisher.connected, 10, "mqtt connected")
                    vb.send(rows(20, 10))
                    await wait_samples(svc, 30)
                    await col.wait(lambda c: any(json.loads(p)["t_s"] == T0 + 30
                                                 for p in c.payloads(f"{root}/cell/0/state")), 10, "newest state")
                online = await retained(port, f"{root}/availability")
                soc = svc.estimator.soc.copy()
            offline = await retained(port, f"{root}/availability")
            broker.stop()
            return online, offline, soc
        finally:
            vb.shutdown()

    online, offline, soc = run_async(main(), 40)
    assert online is not None and bytes(online.payload) == b"online"
    assert offline is not None and bytes(offline.payload) == b"offline"
    assert_state_file_valid(Path(cfg.state.path), soc=soc)


def test_broker_down_mid_run_keeps_can_output(broker_factory, tmp_path):
    broker = broker_factory()
    ch = channel()
    cfg = make_cfg(tmp_path, ch, mqtt_port=broker.port)
    root = f"bms/{PACK}"
    ref = Offline().feed(rows(0, 20, close=False) + rows(20, 20, close=False) + rows(40, 10))

    async def main():
        vb = VBus(ch)
        try:
            async with running(cfg) as svc:
                async with Collector(broker.port, (f"{root}/#",)) as col:
                    vb.send(rows(0, 20, close=False))
                    await col.wait(lambda c: any(json.loads(p)["t_s"] == T0 + 19
                                                 for p in c.payloads(f"{root}/cell/0/state")), 10, "states")
                broker.stop()
                await wait_until(lambda: not svc.publisher.connected, 10, "disconnect")
                vb.send(rows(20, 20, close=False))
                await wait_samples(svc, 39)
                # the estimator and the CAN output went on without the broker
                await vb.wait_outputs(CELL_STATE_IDS, 2 * N * 39)
                assert svc.publisher.counters.disconnects >= 1
                broker.start()
                async with Collector(broker.port, (f"{root}/#",)) as col:
                    await wait_until(lambda: svc.publisher.connected, 10, "reconnected")
                    vb.send(rows(40, 10))
                    await wait_samples(svc, 50)
                    await col.wait(lambda c: any(json.loads(p)["t_s"] == T0 + 50
                                                 for p in c.payloads(f"{root}/cell/5/state")), 10, "states again")
                    p = json.loads([x for x in col.payloads(f"{root}/cell/5/state")][-1])
                got = [(m.arbitration_id, bytes(m.data))
                       for m in await vb.wait_outputs(CELL_STATE_IDS | PACK_IDS, (2 * N + 2) * 50)]
                soc = svc.estimator.soc.copy()
            return got, p, soc
        finally:
            vb.shutdown()

    got, last_payload, soc = run_async(main(), 50)
    assert got == [f for s in ref.steps for f in s.frames]
    assert last_payload["soc"] == ref.est.soc[5]
    np.testing.assert_array_equal(soc, ref.est.soc)
    assert_state_file_valid(Path(cfg.state.path), soc=soc)


FOXBMS_DBC = foxbms_dbc_path()  # (tests.conftest)


@pytest.mark.skipif(FOXBMS_DBC is None, reason="foxBMS DBC not found (../shared/dbc/foxbms/foxbms.dbc or $BMS_FOXBMS_DBC)")
@pytest.mark.parametrize("staleness_s, used_s, warned", [(None, 10.8, False), (5.0, 5.0, True), (8.0, 8.0, False)])
def test_the_staleness_follows_the_mappings_cell_cycle_unless_set(tmp_path, staleness_s, used_s, warned):
    """The foxBMS preset's cell frames come round every 5.4 s (``cell_cycle_s``, the DBC's cycle time);
    with the default ``estimator.staleness_s`` of 5 s every cell read stale in about one sample of 13 on a
    healthy bus (its SOC then goes without the voltage's correction), with nothing saying why. Unset, the
    staleness is now twice the mapping's cell cycle; set below the cycle, the service says so once at start,
    naming both settings; set above it, it is used and quiet."""
    data = config_data(tmp_path, channel(), can={"dbc": str(FOXBMS_DBC), "mapping": "foxbms",
                                                  "output": {"enabled": False}})
    data["estimator"] = {} if staleness_s is None else {"staleness_s": staleness_s}  # None: not in the file
    cfg = ServiceConfig(**data)
    with capture_logs() as logs:
        svc = Service(cfg)
    assert svc.sampler.staleness_s == pytest.approx(used_s)
    said = [e for e in logs if e.get("config_key") == "estimator.staleness_s"]
    assert len(said) == int(warned)
    if warned:
        assert said[0]["log_level"] == "warning"
        assert (said[0]["staleness_s"], said[0]["cell_cycle_s"]) == (5.0, 5.4)


def test_pack_ocv_csv_takes_gzipped_tables(tmp_path, capsys):
    """pack.ocv_csv, as --ocv, reads a .csv.gz table (before: "not UTF-8 text (invalid start byte at byte 1)")."""
    import gzip

    gz = tmp_path / "ocv.csv.gz"
    gz.write_bytes(gzip.compress(ocv_table("panasonic-18650pf").read_bytes()))
    config = tmp_path / "gz.toml"
    config.write_text(f"[pack]\nn_cells = 4\nocv_csv = ['{gz}']\n[state]\npath = '{tmp_path / 'state.npz'}'\n")
    assert cli_main(["run", "--config", str(config), "--check-config"]) == 0, capsys.readouterr().err
    config.write_text(f"[pack]\nn_cells = 4\nocv_csv = '{gz}'\n[state]\npath = '{tmp_path / 'state.npz'}'\n")
    assert cli_main(["run", "--config", str(config), "--check-config"]) == 0, capsys.readouterr().err


def test_bad_config_exits_2_naming_each_field(tmp_path, capsys):
    state = tmp_path / "state.npz"
    bad = tmp_path / "bad.toml"
    bad.write_text(
        "[pack]\nn_cells = 4\n"
        "[mqtt]\nport = 70000\n"
        f"[state]\npath = '{state}'\n"
        "[estimator.core]\nwindw = 20\nforgetting = 1.5\n"
    )
    assert cli_main(["run", "--config", str(bad)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert any(line.strip().startswith("mqtt.port:") for line in err)
    assert any(line.strip().startswith("estimator.core.windw: Extra inputs are not permitted") for line in err)
    assert sum(line.strip().startswith("estimator.core.forgetting: Input should be less than or equal to 1")
               for line in err) == 1

    bad.write_text(f"[pack]\nn_cells = 4\nocv_csv = '{tmp_path / 'missing.csv'}'\n"
                   "[can]\nmapping = 'no-such-preset'\n"
                   f"[state]\npath = '{state}'\n")
    assert cli_main(["run", "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "pack.ocv_csv:" in err and "can.mapping:" in err
    # a path to no table, or to a folder, alone is a configuration mistake too (exit 2, not 3), naming key and path
    for where, what in ((tmp_path / "missing.csv", "no such file"), (tmp_path, "is a directory")):
        bad.write_text(f"[pack]\nn_cells = 4\nocv_csv = '{where}'\n[state]\npath = '{state}'\n")
        assert cli_main(["run", "--config", str(bad), "--check-config"]) == 2
        err = capsys.readouterr().err
        assert f"pack.ocv_csv: {where}: {what}" in err and "Errno" not in err, err
    # a malformed OCV table alone is a data error: exit 3, naming the file, line and column
    table = tmp_path / "bad_ocv.csv"
    table.write_text("soc,ocv_v\n0,abc\n1,4.1\n")
    bad.write_text(f"[pack]\nn_cells = 4\nocv_csv = '{table}'\n[state]\npath = '{state}'\n")
    assert cli_main(["run", "--config", str(bad)]) == 3
    err = capsys.readouterr().err
    assert "pack.ocv_csv:" in err and "bad_ocv.csv: line 2" in err and "Traceback" not in err
    assert cli_main(["run", "--config", str(tmp_path / "nope.toml")]) == 2
    assert "not found" in capsys.readouterr().err
    assert not state.exists()  # nothing was started
    with pytest.raises(ConfigError) as exc:
        soc_config_from_core({"identifier": {"window": "ten"}, "c0_window_s": -1, "capacity_soc_update": "guess"})
    assert {p.split(":")[0] for p in exc.value.problems} == {"estimator.core.identifier.window",
                                                            "estimator.core.c0_window_s",
                                                            "estimator.core.capacity_soc_update"}
    good = soc_config_from_core({"window": 30, "identifier": {"forgetting": 0.999}, "estimate_capacity": False})
    assert good.identifier.window == 30 and good.identifier.forgetting == 0.999 and not good.estimate_capacity


@pytest.mark.parametrize("kind", ["garbage", "other_pack", "other_config"])
def test_unusable_state_file_means_fresh_start(tmp_path, kind):
    path = tmp_path / "state.npz"
    if kind == "garbage":
        path.write_bytes(b"PK\x03\x04 this is not a zip archive at all")
        aside = "corrupt"
    else:
        est = SocEstimator(N, ocv(), CAPACITY_AH, 1.0, initial_soc=0.3)
        meta = {"pack_id": "otherpack" if kind == "other_pack" else PACK, "n_cells": N,
                "fingerprint": "0123456789abcdef"}
        save_state(path, est.state_dict(), meta)
        aside = "foreign"
    frames = rows(0, 30)
    metrics, ref, svc = run_bad_input(tmp_path, frames, 30)
    assert not svc.restored and metrics["bms_state_restored"] == 0
    assert len(list(tmp_path.glob(f"state.npz.{aside}-*"))) == 1  # kept, not deleted
    # a fresh start: SOC from the voltage of the first sample (not 0.3), read as an OCV once the prior's
    # ohmic drop at the cells' temperature is out of it (the drive cycle's first sample is under load)
    from bms_estimator.core.arrhenius import RESISTANCE_ACTIVATION_K, arrhenius_factor
    from bms_estimator.core.identifier import IdentifierConfig

    first = ref.steps[0].sample
    assert abs(first.current_a) > 1.0
    r0 = IdentifierConfig().prior_r0_ohm_ah / CAPACITY_AH * arrhenius_factor(first.cell_temperature_c, 25.0,
                                                                           RESISTANCE_ACTIVATION_K)
    assert ref.steps[0].soc == pytest.approx(ocv().soc_from_ocv(first.cell_voltage_v - r0 * first.current_a))
    assert np.all(np.abs(ref.steps[0].soc - 0.3) > 0.3)


def test_restart_resumes_from_saved_state(tmp_path):
    ch = channel()
    cfg = make_cfg(tmp_path, ch)
    first, second = list(cached_rows(0, 150)), rows(150, 150)
    whole = Offline().feed(restamp(first[:-1] + second))  # the uninterrupted run over the same data
    assert len(whole.steps) == 300

    async def one_run(frames, n):
        vb = VBus(ch)
        try:
            async with running(cfg) as svc:
                vb.send(frames)
                await wait_samples(svc, n)
                socs = [MSG["CellStateA"].decode(m.data) for m in
                        await vb.wait_outputs({MSG["CellStateA"].frame_id}, N * n)]
            return svc, socs
        finally:
            vb.shutdown()

    svc1, _ = run_async(one_run(first, 150), 40)
    assert not svc1.restored
    saved = assert_state_file_valid(Path(cfg.state.path), soc=whole.steps[149].soc)
    assert saved.meta["t_s"] == T0 + 150
    # the SOP/SOE/SOH state (energy counters, commissioning R0) is saved and resumed with the SOC (issue 14)
    sox1 = svc1.pipeline.sox
    assert np.all(sox1.energy_discharged_wh > 0)
    resumed = Service(cfg)
    assert resumed.restore()
    np.testing.assert_array_equal(resumed.pipeline.sox.energy_discharged_wh, sox1.energy_discharged_wh)
    np.testing.assert_array_equal(resumed.pipeline.sox.x_v, sox1.x_v)
    snap = svc1.pipeline.last
    assert np.all(np.isfinite(snap.cells["p_discharge_max_10s_w"])) and np.all(snap.cells["p_discharge_max_10s_w"] > 0)
    assert snap.pack_sox["i_discharge_max_10s_a"] == float(np.min(snap.cells["i_discharge_max_10s_a"]))

    svc2, socs2 = run_async(one_run(second, 150), 40)
    assert svc2.restored
    # continuous: the first estimate after the restart follows the last one before it...
    svc2_first = np.array([d["Soc"] / 100 for d in socs2[:N]])
    assert np.abs(svc2_first - whole.steps[149].soc).max() < 0.001
    np.testing.assert_allclose(svc2_first, whole.steps[150].soc, atol=0.000125 + 1e-12)
    # ...where a fresh start would have read the OCV under load
    fresh = Offline().feed(second).steps[0].soc
    assert np.abs(fresh - whole.steps[150].soc).min() > 0.005
    # and the resumed run ends exactly where the uninterrupted one does
    np.testing.assert_array_equal(svc2.estimator.soc, whole.est.soc)
    for key in PARAM_KEYS:
        np.testing.assert_array_equal(svc2.estimator.params[key], whole.est.params[key])
    assert_state_file_valid(Path(cfg.state.path), soc=whole.est.soc)


def test_healthz_follows_the_samples_and_metrics_move(tmp_path):
    ch = channel()
    cfg = make_cfg(tmp_path, ch, health={"stale_after_periods": 1.0})

    async def main():
        vb = VBus(ch)
        try:
            async with running(cfg) as svc:
                port = svc.health_port
                assert (await http_get(port, "/healthz"))[0] == 503  # no tick yet
                vb.send(rows(0, 10))
                await wait_samples(svc, 10)
                ok = await http_get(port, "/healthz")
                m1 = await scrape(svc)
                await asyncio.sleep(1.6)  # samples stop arriving
                stale = await http_get(port, "/healthz")
                vb.send(rows(10, 10)[1:])
                await wait_samples(svc, 20)
                again = await http_get(port, "/healthz")
                m2 = await scrape(svc)
            return ok, stale, again, m1, m2
        finally:
            vb.shutdown()

    ok, stale, again, m1, m2 = run_async(main(), 30)
    assert ok[0] == 200 and stale[0] == 503 and "stale" in stale[1] and again[0] == 200
    assert m1["bms_samples_total"] == 10 and m2["bms_samples_total"] == 20
    assert m2["bms_can_frames_decoded_total"] > m1["bms_can_frames_decoded_total"] > 0
    assert m2["bms_can_tx_frames_total"] > m1["bms_can_tx_frames_total"]
    assert m2["bms_last_sample_time_seconds"] == T0 + 20
    assert m2["bms_loop_lag_seconds_count"] > 0 and m2['bms_loop_lag_seconds_bucket{le="1.0"}'] == m2["bms_loop_lag_seconds_count"]
    assert m2["bms_tick_seconds_count"] == 20  # a histogram, not the last value
    assert m2['bms_estimator_state{bms_estimator_state="running"}'] == 1
    # the count starts from the OCV table's own C/20 capacity (the SOC scale), not the stated one
    assert 0.5 < m2['bms_pack_soc{stat="mean"}'] < 1
    assert m2["bms_pack_capacity_ah"] == pytest.approx(ocv().capacity_discharge_ah)
    assert m2["bms_can_bus_up"] == 1 and "CAN " in ok[1] and ": open" in ok[1]  # the bus state in /healthz
    assert m1["bms_healthy"] == 1


def test_sigterm_stops_a_real_process_cleanly(mosquitto, tmp_path):
    state = tmp_path / "state.npz"
    cfg = tmp_path / "config.toml"
    health_port = free_port()
    cfg.write_text(
        f"[pack]\npack_id = '{PACK}'\nn_cells = {N}\ncapacity_ah = {CAPACITY_AH}\n"
        f"[can]\ninterface = 'virtual'\nchannel = '{channel()}'\n"
        f"[mqtt]\nhost = '127.0.0.1'\nport = {mosquitto.port}\nreconnect_min_s = 0.1\nreconnect_max_s = 0.5\n"
        f"[state]\npath = '{state}'\n"
        f"[health]\nport = {health_port}\n"
        "[logging]\nformat = 'json'\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("BMS_")}
    env["PYTHONPATH"] = str(REPO_ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.Popen([sys.executable, "-m", "bms_estimator.cli", "run", "--config", str(cfg)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    root = f"bms/{PACK}"

    async def online():
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            assert proc.poll() is None, proc.stderr.read().decode()
            m = await retained(mosquitto.port, f"{root}/availability", timeout=0.5)
            if m is not None and bytes(m.payload) == b"online":
                return (await http_get(health_port, "/healthz"))[0]
            await asyncio.sleep(0.1)
        raise AssertionError("service never came online")

    try:
        health = run_async(online(), 30)
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = proc.stderr.read().decode()
    assert rc == 0, err
    assert health == 503  # up, but no sample yet
    m = run_async(retained(mosquitto.port, f"{root}/availability"))
    assert m is not None and bytes(m.payload) == b"offline"
    assert_state_file_valid(state)
    events = [json.loads(line)["event"] for line in err.splitlines() if line.startswith("{")]
    assert "service ready" in events and "estimator state saved" in events


def test_run_service_returns_after_the_stop_event(tmp_path):
    cfg = make_cfg(tmp_path, channel(), health={"enabled": False})

    async def main():
        stop = asyncio.Event()
        seen = []
        task = asyncio.create_task(run_service(cfg, stop_event=stop, started=seen.append))
        await wait_until(lambda: seen and seen[0].ready.is_set(), 10, "ready")
        stop.set()
        return await asyncio.wait_for(task, 10), seen[0]

    svc, seen = run_async(main(), 20)
    assert svc is seen and svc.health_port is None
    assert_state_file_valid(Path(cfg.state.path))


def test_systemd_ready_watchdog_and_stopping(tmp_path, monkeypatch):
    """READY=1 once the bus is open; WATCHDOG=1 while ticking; withheld while frames arrive
    without ticks; resumed while the bus is silent; STOPPING=1 at the end."""
    import socket as _socket

    sock_path = tmp_path / "notify.sock"
    srv = _socket.socket(_socket.AF_UNIX, _socket.SOCK_DGRAM)
    srv.bind(str(sock_path))
    srv.setblocking(False)
    monkeypatch.setenv("NOTIFY_SOCKET", str(sock_path))
    monkeypatch.setenv("WATCHDOG_USEC", "100000")  # ping every 50 ms
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    ch = channel()
    # kernel filters off: the frames that arrive without completing a sample are of an unmapped id
    cfg = make_cfg(tmp_path, ch, health={"stale_after_periods": 0.3}, can={"kernel_filters": False})
    got: list[tuple[float, str]] = []

    def drain() -> list[tuple[float, str]]:
        while True:
            try:
                got.append((time.monotonic(), srv.recv(4096).decode()))
            except BlockingIOError:
                return got

    def pings_since(t: float) -> int:
        return sum(1 for ts, m in drain() if ts >= t and "WATCHDOG=1" in m)

    async def main():
        vb = VBus(ch)

        async def receive():  # time-stamp the datagrams as they come
            while True:
                drain()
                await asyncio.sleep(0.005)

        receiver = asyncio.create_task(receive())
        try:
            async with running(cfg) as svc:
                assert any("READY=1" in m for _, m in drain())
                vb.send(rows(0, 5))
                await wait_samples(svc, 5)
                t = time.monotonic()
                await asyncio.sleep(0.15)
                ticking = pings_since(t)
                # frames keep arriving, but none completes a sample: no more pings once stale
                end = time.monotonic() + 1.0
                while time.monotonic() < end:
                    vb.tx.send(can.Message(timestamp=T0 + 6, arbitration_id=0x7FF, is_extended_id=False, data=b"x"))
                    await asyncio.sleep(0.02)
                no_ticks = pings_since(end - 0.3)  # the heartbeat went stale 0.3 s after the last tick
                # a silent bus is not a hung daemon
                await asyncio.sleep(0.6)
                silent = pings_since(time.monotonic() - 0.2)
            return ticking, no_ticks, silent
        finally:
            receiver.cancel()
            vb.shutdown()

    try:
        ticking, no_ticks, silent = run_async(main(), 30)
        msgs = [m for _, m in drain()]
    finally:
        srv.close()
    assert ticking >= 1 and no_ticks == 0 and silent >= 1
    assert any("STOPPING=1" in m for m in msgs)


def test_publish_latency_bench_runs(tmp_path):
    from benchmarks.publish_latency import bench_publish_latency, find_mosquitto

    if find_mosquitto() is None:
        pytest.skip("mosquitto not installed: the bench reports None")
    res = bench_publish_latency(n_cells=12, samples=3, warmup=1, freeze_gc=False)
    assert res is not None and res["samples"] == 3 and 0 < res["p50_ms"] <= res["p99_ms"] <= res["max_ms"] < 5000


def test_ready_at_once_with_the_bus_absent_then_receiving_when_it_appears(tmp_path, monkeypatch):
    """READY=1 does not wait for the CAN interface (an absent can0 used to keep the unit
    'activating' until TimeoutStartSec, then restart it forever): the service is ready at once,
    shows the bus as down in STATUS, /healthz and /metrics, and receives once the bus appears."""
    import threading

    from bms_estimator.can.bus import open_bus

    srv = NotifySocket(tmp_path / "notify.sock", monkeypatch)
    drain, got = srv.drain, srv.got

    ch = channel()
    cfg = make_cfg(tmp_path, ch)
    present = threading.Event()
    attempts = []

    def factory(bus_cfg):
        attempts.append(time.monotonic())
        if not present.is_set():
            raise OSError(19, "No such device")  # what socketcan says for a missing interface
        return open_bus(bus_cfg)

    async def main():
        vb = VBus(ch)
        try:
            async with running(cfg, bus_factory=factory, wait_ready=False) as svc:
                await wait_until(lambda: any("READY=1" in m for m in drain()), 5, "READY=1 with the bus absent")
                ready = next(m for m in got if "READY=1" in m)
                assert "CAN " in ready and "down" in ready
                await wait_until(lambda: len(attempts) >= 3, 5, "open retried in the background")
                assert not svc.bus.is_open and not svc.ready.is_set()
                status, body = await http_get(svc.health_port, "/healthz")
                assert status == 503 and ": down (OSError: [Errno 19] No such device)" in body
                m = await scrape(svc)
                assert m["bms_can_bus_up"] == 0 and m['bms_can_bus_events_total{event="open_failure"}'] >= 3
                assert "down" in svc._status_line()

                present.set()  # the interface appears
                await wait_until(svc.ready.is_set, 5, "bus open")
                vb.send(rows(0, 5))
                await wait_samples(svc, 5)
                status, body = await http_get(svc.health_port, "/healthz")
                assert status == 200 and ": open" in body
                m = await scrape(svc)
                assert m["bms_can_bus_up"] == 1 and m['bms_can_bus_events_total{event="open"}'] == 1
                await wait_until(lambda: any(m.startswith("STATUS=") and ": open" in m for m in drain()), 5,
                                 "STATUS shows the bus open")
        finally:
            vb.shutdown()
            srv.close()

    run_async(main(), 30)


@pytest.mark.parametrize("poison", [{"capacity_ah": 0.0}, {"capacity_ah": -2.9}, {"capacity_ah": float("nan")},
                                    {"soc": 7.0}, {"charge_ah": float("inf")}])
def test_poisoned_state_is_set_aside_not_resumed(tmp_path, poison):
    """A well-formed state file of this very pack and configuration whose values no cell can have (a zero or
    negative capacity, an SOC of 700 %, an infinite charge): resumed, it would survive every restart. It is
    refused with a log line naming the field, kept aside, and the service starts fresh."""
    cfg = make_cfg(tmp_path, channel())
    svc = Service(cfg)
    est = SocEstimator(N, ocv(), CAPACITY_AH, 1.0, initial_soc=0.6, config=svc.soc_config)
    state = est.state_dict()
    for key, value in poison.items():
        state[key] = np.full(N, value)
    save_state(Path(cfg.state.path), state, {"pack_id": PACK, "n_cells": N, "fingerprint": svc.fingerprint})
    good = Service(cfg)
    assert good.restore() is False and not good.restored
    assert not Path(cfg.state.path).exists()
    assert len(list(tmp_path.glob("state.npz.foreign-*"))) == 1  # kept for a look, never overwritten
    fresh = good.estimator
    assert np.all(fresh.capacity_ah > 0) and not np.isfinite(fresh.soc).any()  # SOC comes from the first sample
    with pytest.raises(ValueError, match=f"state field '{next(iter(poison))}'"):
        SocEstimator(N, ocv(), CAPACITY_AH, 1.0, config=svc.soc_config).load_state_dict(state)
