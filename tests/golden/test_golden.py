"""The service's outputs on a replayed log are those recorded from the code before the
restructuring into a pipeline (scripts/record_golden.py): CAN frames byte for byte, MQTT
state values to floating-point rounding (payloads may carry added keys, the CAN output added frames)."""

from __future__ import annotations

import gzip
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from golden_run import run_golden  # noqa: E402

from bms_estimator.can.dbc import load_db  # noqa: E402

N_CELLS = 4
#: a signal that depends on the wall clock, not on the log
_CLOCK_SIGNALS = {"UptimeS"}


def _load(name: str) -> list:
    with gzip.open(HERE / name, "rt") as fh:
        return [json.loads(line) for line in fh]


def _by_topic(payloads: list) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = defaultdict(list)
    for topic, text in payloads:
        out[topic].append(json.loads(text))
    return out


def _same(got, want) -> bool:
    """Equal, floats to the last few bits: numpy builds differ in how they order a sum (SIMD width,
    pairwise blocks), so a value that is bit-identical on one machine may differ in its last bits on
    another, and the recursive identifier carries that on (measured up to 4e-12 relative over this log).
    A real change of the estimator moves values by far more than 1e-6."""
    if isinstance(want, float) and isinstance(got, float):
        return math.isclose(got, want, rel_tol=1e-6, abs_tol=1e-9)
    return got == want


def test_outputs_match_the_recording() -> None:
    frames, payloads = run_golden(HERE / "pack4.log.gz", N_CELLS)
    want_frames = _load("can_out.jsonl.gz")
    db = load_db(None)
    # the SOP/SOE/SOH frames are in the recording: one set per sample, compared like the others
    from bms_estimator.service.schema import CAN_PACK_SOX_SIGNALS

    sox_ids = {db.get_message_by_name(m).frame_id for m in CAN_PACK_SOX_SIGNALS}
    n_sox = sum(f[0] in sox_ids for f in frames)
    summaries = sum(f[0] == db.get_message_by_name("PackSummary").frame_id for f in frames)
    assert n_sox == len(sox_ids) * summaries > 0
    assert len(frames) == len(want_frames)
    clocked = {m.frame_id for m in db.messages if _CLOCK_SIGNALS & {s.name for s in m.signals}}
    for k, (got, want) in enumerate(zip(frames, want_frames)):
        assert got[0] == want[0], f"frame {k}: id {got[0]:#x} != {want[0]:#x}"
        if got[0] in clocked:
            msg = db.get_message_by_frame_id(got[0])
            g, w = msg.decode(bytes.fromhex(got[1])), msg.decode(bytes.fromhex(want[1]))
            for name in _CLOCK_SIGNALS:
                g.pop(name, None), w.pop(name, None)
            assert g == w, f"frame {k} ({msg.name})"
        else:
            assert got[1] == want[1], f"frame {k} ({db.get_message_by_frame_id(got[0]).name})"

    got_mqtt, want_mqtt = _by_topic(payloads), _by_topic(_load("mqtt_out.jsonl.gz"))
    assert set(got_mqtt) == set(want_mqtt)
    compared = 0
    for topic, wants in want_mqtt.items():
        gots = got_mqtt[topic]
        assert len(gots) == len(wants), topic
        for g, w in zip(gots, wants):
            for key, value in w.items():
                assert key in g, f"{topic}: key {key!r} missing"
                assert type(g[key]) is type(value) and _same(g[key], value), f"{topic} t_s={w.get('t_s')}: {key}: {g[key]!r} != {value!r}"
                compared += 1
    assert compared > 20_000


def test_a_per_cell_output_is_one_schema_line(monkeypatch):
    """A per-cell value the estimator offers reaches the snapshot and the MQTT payload from one
    CellField line (as an SOC uncertainty will)."""
    import numpy as np

    from bms_estimator.core.soc import SocEstimator
    from bms_estimator.service import schema

    monkeypatch.setattr(SocEstimator, "soc_sigma", property(lambda self: np.full(self.n_cells, 0.01)), raising=False)
    monkeypatch.setattr(schema, "CELL_FIELDS", (*schema.CELL_FIELDS, schema.CellField("soc_sigma", "SOC sigma", estimator="soc_sigma")))
    monkeypatch.setattr(schema, "CELL_KEYS", tuple(f.key for f in schema.CELL_FIELDS))
    import bms_estimator.service.pipeline as pipeline

    monkeypatch.setattr(pipeline, "CELL_FIELDS", schema.CELL_FIELDS)
    frames, payloads = run_golden(HERE / "pack4.log.gz", N_CELLS, max_frames=20_000)
    cell = [json.loads(p) for t, p in payloads if "/cell/" in t]
    assert cell and all(c["soc_sigma"] == 0.01 for c in cell)
