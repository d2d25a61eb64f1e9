"""The service's per-frame path (FrameDecoder -> SampleAssembler) as the reference for bulk decode; a batch configuration."""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np

from bms_estimator.can.decoder import FrameDecoder
from bms_estimator.can.sampler import SampleAssembler
from bms_estimator.fleet.frames import EXTENDED_FLAG, FrameTable
from bms_estimator.fleet.samples import SampleArrays


def service_sampler(n_cells: int, period_s: float = 1.0, staleness_s: float = 2.5) -> SampleAssembler:
    """A sampler with the service's settings (service/daemon.py)."""
    return SampleAssembler(n_cells, period_s=period_s, staleness_s=staleness_s,
                           max_gap_s=max(5.0, staleness_s, 2.0 * period_s), rewind_s=max(5.0, 2.0 * period_s))


def messages(frames: FrameTable) -> list[can.Message]:
    out = []
    for i in range(len(frames)):
        key = int(frames.key[i])
        out.append(can.Message(timestamp=float(frames.t_s[i]), arbitration_id=key & 0x1FFFFFFF,
                               is_extended_id=bool(key & EXTENDED_FLAG),
                               data=bytes(frames.data[i, : int(frames.length[i])])))
    return out


def service_samples(decoder: FrameDecoder, sampler: SampleAssembler, msgs) -> SampleArrays:
    """What Pipeline.process_frame feeds the estimator, frame by frame."""
    out = []
    for m in msgs:
        out.extend(sampler.feed_frame(decoder.decode(m), m.timestamp))
    counters = {**decoder.counters.as_dict(), **sampler.counters.as_dict()}
    return SampleArrays.from_samples(out, sampler.n_cells, sampler.period_s, counters)


FIELDS = ("t_s", "current_a", "current_valid", "current_coverage", "cell_voltage_v", "cell_temperature_c",
          "valid", "pack_voltage_v")


def assert_same_samples(a: SampleArrays, b: SampleArrays) -> None:
    assert len(a) == len(b), (len(a), len(b))
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.shape == y.shape, f
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), f"{f} differs at {np.argwhere(~((x == y) | (np.isnan(x) & np.isnan(y)) if x.dtype.kind == 'f' else x == y))[:5]}"


def write_batch_config(d: Path, n_cells: int, channel: str) -> Path:
    """``d/config.toml``: a pack of ``n_cells`` shipped LG HG2 cells (3.0 Ah, the 25 degC OCV sample), no
    outputs, the state file in ``d`` (kept 10 days)."""
    ocv = Path(__file__).parents[2] / "bms_estimator" / "samples" / "lg-hg2_25degC_ocv.csv"
    cfg = d / "config.toml"
    cfg.write_text(f"""
[pack]
pack_id = "car1"
n_cells = {n_cells}
capacity_ah = 3.0
ocv_csv = "{ocv}"
[can]
interface = "virtual"
channel = "{channel}"
output = {{ enabled = false }}
[mqtt]
enabled = false
[health]
enabled = false
[state]
path = "{d / 'state.npz'}"
max_age_s = 864000
""")
    return cfg
