"""A parallel group in the service (``estimator.sop.n_parallel``): ``k`` equal cells in parallel per series
element, ``pack.capacity_ah`` one cell's.  Each cell carries the pack current / k (core.sop's module
docstring), so k cells in parallel carrying k times a measured cell's current must give that cell's SOC and
model, and pack figures k times the single cell's (current limits, energy).  Measured LG HG2 la92 sample."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bms_estimator.can.dbc import load_project_db
from bms_estimator.can.decoder import FrameDecoder
from bms_estimator.can.sampler import Sample, SampleAssembler
from bms_estimator.core.soc import SocEstimator
from bms_estimator.core.sop import SopConfig
from bms_estimator.core.sox import SoxConfig, SoxEstimator
from bms_estimator.data import load_recording
from bms_estimator.ocv_table import read_ocv_table
from bms_estimator.service.pipeline import Pipeline

SAMPLES = Path(__file__).parents[2] / "bms_estimator" / "samples"
N_SECONDS = 1500


def _run(k: int) -> tuple[np.ndarray, np.ndarray, dict]:
    rec = load_recording(SAMPLES / "lg-hg2_25degC_la92_1s.csv.gz")
    ocv = read_ocv_table(SAMPLES / "lg-hg2_25degC_ocv.csv")
    est = SocEstimator(1, ocv, 3.0, 1.0, initial_soc=None)
    sox = SoxEstimator(1, 1.0, SoxConfig(sop=SopConfig(n_parallel=k)))
    pipe = Pipeline(FrameDecoder(load_project_db(), "default", 1), SampleAssembler(1, 1.0, 2.5), est, sox=sox, clock=lambda: 0.0, wall_clock=lambda: 0.0)
    socs, r0 = [], []
    for j in range(N_SECONDS):
        snap = pipe.tick(Sample(t_s=float(j + 1), current_a=k * float(rec.current_a[j]),
                                cell_voltage_v=np.array([rec.voltage_v[j]]),
                                cell_temperature_c=np.array([rec.temperature_c[j]]), valid=np.array([True]),
                                pack_voltage_v=float(rec.voltage_v[j])))
        assert snap is not None
        socs.append(snap.cells["soc"][0])
        r0.append(snap.cells["r0_ohm"][0])
    return np.array(socs), np.array(r0), dict(snap.pack_sox)


def test_k_cells_in_parallel_are_k_times_one_cell():
    soc1, r01, pack1 = _run(1)
    soc2, r02, pack2 = _run(2)
    # each of the two cells carries half the pack current: the measured cell's SOC and resistance
    np.testing.assert_allclose(soc2, soc1, atol=1e-9)
    np.testing.assert_allclose(r02, r01, rtol=1e-9, equal_nan=True)
    # the pack's current limits and energy are twice the one cell's
    for key in ("i_discharge_max_10s_a", "i_charge_max_10s_a", "energy_left_wh", "energy_discharged_wh"):
        assert pack2[key] == pytest.approx(2.0 * pack1[key], rel=1e-6), key


def test_batch_takes_a_parallel_groups_pack_current(tmp_path):
    """``batch`` on a recording of the pack current of 2 cells in parallel (n_parallel = 2, pack.capacity_ah
    one cell's): it refused the 2.8 h drive ('its coulomb count spans 5.2 Ah, 1.9 times pack.capacity_ah'),
    and would have counted the SOC twice too fast.  Now the measured cell's SOC, and twice its pack limits."""
    import gzip

    from bms_estimator.fleet.drive import run_drive

    from tests.fleet.fleet_helpers import write_batch_config

    lines = gzip.open(SAMPLES / "lg-hg2_25degC_la92_1s.csv.gz", "rt").read().splitlines()
    runs = {}
    for k in (1, 2):
        d = tmp_path / f"k{k}"
        (d / "car1").mkdir(parents=True)
        rows = [lines[0]] + [",".join([r[0], f"{k * float(r[1]):.9g}", *r[2:]]) for r in
                             (line.split(",") for line in lines[1:])]
        log = d / "car1" / "drive.csv"
        log.write_text("\n".join(rows) + "\n")
        cfg = write_batch_config(d, 1, f"par{k}")
        cfg.write_text(cfg.read_text() + f"[estimator.sop]\nn_parallel = {k}\n")
        res, _, est = run_drive(log, str(cfg), d / "out", "car1", write=False, sox=True)
        assert res.status == "ok", res
        runs[k] = est
    np.testing.assert_allclose(runs[2].cells["soc"], runs[1].cells["soc"], atol=1e-9)
    np.testing.assert_allclose(runs[2].pack["i_discharge_max_10s_a"], 2.0 * runs[1].pack["i_discharge_max_10s_a"],
                               rtol=1e-9)
