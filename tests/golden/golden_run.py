"""Drive the service's frame path over a log and collect what it sends (see scripts/record_golden.py)."""

from __future__ import annotations

import gzip
import tempfile
from pathlib import Path

import can


class _CapturingBus:
    is_open = True

    def __init__(self) -> None:
        self.frames: list[can.Message] = []

    def send_many(self, frames) -> None:
        self.frames.extend(frames)


def read_log(path: Path) -> list[can.Message]:
    with tempfile.TemporaryDirectory() as d:
        plain = Path(d) / "in.log"
        plain.write_bytes(gzip.decompress(Path(path).read_bytes()))
        return list(can.LogReader(str(plain)))


def run_golden(log: Path, n_cells: int, max_frames: int | None = None) -> tuple[list[list], list[list]]:
    """``([[arbitration_id, data hex], ...], [[topic, payload json], ...])`` in sending order."""
    from bms_estimator.service.config import ServiceConfig
    from bms_estimator.samples import ocv_table
    from bms_estimator.service.daemon import Service

    with tempfile.TemporaryDirectory() as d:
        cfg = ServiceConfig(
            pack={"n_cells": n_cells, "capacity_ah": 3.0, "ocv_csv": str(ocv_table("lg-hg2"))},
            state={"path": str(Path(d) / "state.npz"), "save_interval_s": 86400},
            health={"enabled": False},
        )
        svc = Service(cfg)
        bus = _CapturingBus()
        svc.bus = bus  # type: ignore[assignment]
        payloads: list[list] = []
        svc.publisher._put = lambda items: payloads.extend([t, p] for t, p, _ in items)  # type: ignore[method-assign]
        for msg in read_log(log)[:max_frames]:
            svc.pipeline.process_frame(msg)
    frames = [[m.arbitration_id, bytes(m.data).hex()] for m in bus.frames]
    return frames, payloads
