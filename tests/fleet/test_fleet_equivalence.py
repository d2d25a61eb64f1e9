"""The same encoded logs through `replay` -> the service and through `batch`: equal sample by sample.

The service side is the real daemon (Service.run: ResilientBus on a python-can virtual bus,
FrameDecoder, SampleAssembler, SocEstimator, state saved at stop and restored at start); the
log is replayed at max speed with the log's timestamps (open_replay_bus), flow-controlled on
the service's receive counter so that no frame is dropped. The batch side is
fleet/drive.py's run_drive/run_vehicle (bulk decode, the same estimator).

Tolerance: none. Per-cell SOC and parameters are compared with array_equal (NaN = NaN):
bulk assembly reproduces the sampler's samples bit for bit (tests/fleet/test_fleet_decode.py)
and the estimator steps are the service's own Pipeline.tick, so any difference is a bug.
Chained: drive 2 starts from the state the service saved at the end of drive 1 (its state
file) and from the state batch carried (the same state_dict round trip).

SOX (``batch --sox``): the service always runs its SoxEstimator; batch with ``sox=True`` gives
its per-cell outputs (every key the snapshot carries) bit for bit too, chained through the
state file's SOX part, and leaves the estimator's outputs as they are without it. Its pack
figures (``DriveEstimate.pack``, the pack Parquet) are the snapshots' ``pack_sox`` (what the
pack payload and the CAN pack frames carry), every key, sample by sample, also without tolerance.
"""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from bms_estimator.fleet.drive import run_drive, run_vehicle
from bms_estimator.replay.encode_log import encode_log
from bms_estimator.replay.replay import open_replay_bus, read_log, replay_messages
from bms_estimator.service.config import load_config

from .fleet_helpers import write_batch_config

N_CELLS = 5
KEYS = ("soc", "r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "c0_v", "capacity_ah", "temperature_c", "voltage_v")
UNDEFINED_HERE = ("soh_capacity", "soh_capacity_sigma", "soh_resistance", "r0_ref_ohm")
SAMPLE = Path(__file__).parents[2] / "bms_estimator" / "samples" / "lg-hg2_25degC_udds_1s.csv.gz"


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet-eq")
    logs = []
    for i, (dur, soc0, suffix) in enumerate([(420.0, 1.0, ".log"), (300.0, 0.9, ".blf")]):
        out = d / "car1" / f"drive{i}{suffix}"
        out.parent.mkdir(exist_ok=True)
        encode_log(SAMPLE, out, N_CELLS, initial_soc=soc0, duration_s=dur, reference_capacity_ah=3.0, seed=i)
        logs.append(out)
    cfg = write_batch_config(d, N_CELLS, f"fleet-eq-{time.monotonic_ns()}")
    return logs, cfg


async def _service_drive(cfg_path: Path, log: Path) -> list[tuple[float, dict[str, np.ndarray], dict[str, float]]]:
    """(t_s, per-cell outputs, pack SOX figures) of every snapshot of the daemon on ``log``."""
    from bms_estimator.service.daemon import Service

    cfg = load_config(cfg_path)
    svc = Service(cfg)
    snaps: list[tuple[float, dict[str, np.ndarray], dict[str, float]]] = []
    svc.pipeline.add_hook(lambda s: snaps.append((s.t_s, {k: np.array(v, copy=True) for k, v in s.cells.items()},
                                                  dict(s.pack_sox))))
    stop = asyncio.Event()
    task = asyncio.create_task(svc.run(stop))
    await asyncio.wait_for(svc.ready.wait(), 20)
    msgs = list(read_log(log))
    tx = open_replay_bus("virtual", cfg.can.channel)

    def gate(items):
        for sent, m in enumerate(items):
            while sent - svc.bus.counters.rx_frames > 5000:
                time.sleep(0.001)
            yield m

    th = threading.Thread(target=replay_messages, args=(gate(msgs), tx, "max"), daemon=True)
    th.start()
    try:
        while svc.decoder.counters.frames < len(msgs):
            await asyncio.sleep(0.02)
            assert svc.bus.counters.rx_dropped == 0
    finally:
        th.join(10)
        stop.set()
        await asyncio.wait_for(task, 60)
        tx.shutdown()
    return snaps


def _assert_equal(snaps, est, keys=KEYS) -> None:
    assert len(snaps) == len(est) > 100
    assert np.array_equal([t for t, *_ in snaps], est.t_s)
    for key in keys:
        # a SOX key is missing from the snapshots before the drive's first update: NaN in the batch
        ref = np.stack([c.get(key, np.full(N_CELLS, np.nan)) for _, c, _ in snaps])
        assert np.array_equal(ref, est.cells[key], equal_nan=True), key
        # a value somewhere (time to full is inf while discharging; the SOH figures are undefined in 7 min
        # from a full cell: test_fleet_sox.py has them)
        assert (np.isfinite(ref) if key in KEYS else ~np.isnan(ref)).any() or key in UNDEFINED_HERE, key


def _assert_pack_equal(snaps, est) -> None:
    """Every pack SOX key of the snapshots (``snap.pack_sox``) equals batch's pack series, sample by sample."""
    keys = list(snaps[-1][2])
    assert len(keys) >= 19 and list(est.pack) == keys
    assert len(snaps) == len(est) and all(set(p) in (set(), set(keys)) for *_, p in snaps)
    for key in keys:
        ref = np.array([p.get(key, np.nan) for *_, p in snaps])  # none before the first update: NaN
        assert np.array_equal(ref, est.pack[key], equal_nan=True), key
        # a value somewhere (time to full is inf while discharging; the SOH figures are undefined here, as the cells')
        assert (~np.isnan(ref)).any() or key in ("soh_capacity_min", "soh_resistance_max"), key


def test_batch_equals_replay_through_the_service_chained(drives, tmp_path):
    logs, cfg = drives
    service = [asyncio.run(_service_drive(cfg, log)) for log in logs]  # drive 2 restores drive 1's state file
    res1, state1, est1 = run_drive(logs[0], str(cfg), tmp_path, "car1")
    res2, _, est2 = run_drive(logs[1], str(cfg), tmp_path, "car1", state1)
    assert (res1.status, res2.status) == ("ok", "ok")
    _assert_equal(service[0], est1)
    _assert_equal(service[1], est2)
    assert est1.sox_keys == () and "soh_resistance" not in est1.cells  # without sox: no SOX outputs
    assert est1.pack == {} and est1.pack_energy_wh == {} and res1.pack_parquet == "" and res1.pack == {}
    # with SOX: the service's per-cell SOX outputs, sample by sample, chained through the state's SOX part
    res1s, state1s, sox1 = run_drive(logs[0], str(cfg), tmp_path, "car1", sox=True)
    res2s, _, sox2 = run_drive(logs[1], str(cfg), tmp_path, "car1", state1s, sox=True)
    assert any(k.startswith("sox.") for k in state1s) and not any(k.startswith("sox.") for k in state1)
    sox_keys = tuple(k for k in service[0][-1][1] if k not in est1.cells and k != "stale")
    assert len(sox_keys) >= 20 and sox1.sox_keys == sox2.sox_keys == sox_keys
    _assert_equal(service[0], sox1, KEYS + sox_keys)
    _assert_equal(service[1], sox2, KEYS + sox_keys)
    # and the pack figures the service publishes (pack payload, CAN), also chained
    _assert_pack_equal(service[0], sox1)
    _assert_pack_equal(service[1], sox2)
    import pyarrow.parquet as pq

    pack_table = pq.read_table(res2s.pack_parquet)
    assert pack_table.column_names == ["t_s", "current_a", *sox2.pack]
    for key in sox2.pack:
        assert np.array_equal(pack_table.column(key).to_numpy(), sox2.pack[key], equal_nan=True), key
    for key in KEYS:  # the SOX part only reads the estimator
        assert np.array_equal(sox2.cells[key], est2.cells[key], equal_nan=True), key
    # the drive's energy out: the service's cumulative counter's change over drive 2
    out = service[1][-1][1]["energy_discharged_wh"] - service[0][-1][1]["energy_discharged_wh"]
    assert np.array_equal(res2s.cells["energy_discharged_wh"], out.tolist()) and (out > 0).all()
    # the pack's: the change of the pack payload's counter over drive 2 (up to the sums' order: one rounding)
    pack_out = service[1][-1][2]["energy_discharged_wh"] - service[0][-1][2]["energy_discharged_wh"]
    assert res2s.pack["pack_energy_discharged_wh"] == pytest.approx(pack_out, rel=1e-12) and pack_out > 0
    # the chain matters: drive 2 from a fresh state differs from the service's restored run
    _, _, fresh = run_drive(logs[1], str(cfg), tmp_path, "car1", None)
    assert not np.array_equal(fresh.cells["soc"], est2.cells["soc"], equal_nan=True)
    # run_vehicle chains in time order (both logs start at t=0: by name) and writes the Parquet
    results = run_vehicle([str(p) for p in reversed(logs)], str(cfg), tmp_path / "v", "car1")
    assert [Path(r.path).name for r in results] == [p.name for p in logs]
    table = pq.read_table(results[1].parquet)
    soc = table.column("soc").to_numpy().reshape(-1, N_CELLS)
    assert np.array_equal(soc, est2.cells["soc"], equal_nan=True)
