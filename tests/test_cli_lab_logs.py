"""Recordings as other labs and loggers write them (absolute timestamps, another test order, ...): the offline
commands read them to the same result as the data set's layout, or refuse them in one line, and what they write
reads back (LG HG2 sample, Kollmeyer et al., CC BY 4.0)."""

from __future__ import annotations

import numpy as np
import pytest

from bms_estimator.cli.__main__ import main
from bms_estimator.data import CellRecording, load_recording, save_recording
from bms_estimator.samples import drive_cycle, ocv_table


def _la92_head(tmp_path, n: int, t0: float, name: str):
    rec = load_recording(drive_cycle("lg-hg2", "la92"))
    part = CellRecording(rec.time_s[:n] + t0, rec.current_a[:n], rec.voltage_v[:n], rec.temperature_c[:n], name)
    return save_recording(part, tmp_path / name)


def test_the_soc_trace_keeps_an_absolute_time_base(tmp_path, capsys):
    """A log stamped in Unix time (s): the trace wrote time_s with 6 significant digits, 1.7e+09 on every row,
    so it could not be put beside the log it came from."""
    t0 = 1.7e9 + 0.25
    data = _la92_head(tmp_path, 1500, t0, "epoch.csv")
    trace = tmp_path / "trace.csv"
    assert main(["soc", str(data), "--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3.0",
                 "--reference-capacity-ah", "2.8", "--start-s", "100", "--trace", str(trace)]) == 0
    rows = np.genfromtxt(trace, delimiter=",", names=True)
    rec = load_recording(data)
    np.testing.assert_allclose(rows["time_s"], rec.time_s, rtol=0, atol=1e-6)
    assert np.all(np.diff(rows["time_s"]) == pytest.approx(1.0))
    assert np.isnan(rows["soc"][rows["time_s"] < rec.time_s[0] + 100 - 1e-6]).all()
