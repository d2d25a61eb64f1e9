"""A measured single-cell recording -> the CAN traffic of a whole pack (``bms-estimator encode-log``).

What is made
------------
The input is one measured cell (``time_s,current_a,voltage_v[,temperature_c]``,
current positive = charge; 0.1 s data is averaged to 1 s by
:func:`~bms_estimator.data.load_recording`). The output is the bus traffic a
series pack of ``n_cells`` such cells would put on the project's CAN bus
(``dbc/bms_estimator.dbc``), at the rates the DBC declares:

==================  ==========  ==========================================================
frame               period      content
==================  ==========  ==========================================================
PackMeasurement     10 ms       pack current (= the cell current, series pack) and pack
                                voltage (sum of the cell voltages), alive counter, CRC-8
CellVoltages        100 ms      3 cells per frame, ``CellIndexBase`` = 0, 3, 6, ...; the
                                ``ceil(n/3)`` frames of one round are spread evenly over
                                the 100 ms
CellTemperatures    1 s         6 cells per frame, ``CellIndexBase`` = 0, 6, ...; spread
                                evenly over the second
==================  ==========  ==========================================================

Time base: frame times are integer microseconds from ``t0_s`` (default 0, so the
``.log``, ``.asc`` and ``.blf`` files read back with identical timestamps: an ASC
file only keeps times relative to its start). Sample ``k`` of the recording covers
``[t0 + k dt, t0 + (k+1) dt)``; every frame in that interval carries sample ``k``.
At equal times the order is current, voltages, temperatures.

End-to-end protection: every frame carries the DBC's alive counter, +1 per frame of its
id and ``CellIndexBase`` from 0, and PackMeasurement its CRC-8, written by
:class:`~bms_estimator.can.e2e.E2EStamper` from the project preset's ``[e2e.*]`` checks, so
the service's default mapping accepts every frame.

Current (charge-exact). The recording's sample is the mean current over its
period. The 10 ms frames hold it, dithered by at most 1 mA so that the charge is
exact: frame ``m`` carries ``round(Q(t_{m+1})) - round(Q(t_m))`` mA, ``Q`` the
cumulative charge in mA x 10 ms. Any run of frames therefore carries the
recording's charge to within one raw step (10 uA s) in total, and the service's
zero-order-hold integration gives each 1 s sample's mean current to 1e-5 A.

Voltages and temperatures are held over their sample (0.1 mV and 0.5 degC DBC
steps). Every cell gets the measured temperature (NotAvailable when the file has
none).

The cells
---------
* Cell 0 carries the measured voltage unchanged (up to the 0.1 mV DBC step).
* The other cells are simulated from the model identified on the measured data:

  1. reference capacity ``Q_ref``: :func:`~bms_estimator.analysis.reference_capacity`
     over the whole file (measured when the file ends at rest); otherwise the online
     SOC estimator's effective capacity (as ``bms-estimator compare`` does); or
     ``reference_capacity_ah`` when given;
  2. reference SOC path: coulomb counting from ``initial_soc`` with ``Q_ref``;
  3. :func:`~bms_estimator.analysis.run_identification` (continuous-time LIF) along
     it, :func:`~bms_estimator.analysis.soc_lookup_table` (median per 2 % SOC bin);
  4. residual ``r(t) = v_measured(t) - v_model(t)``, ``v_model`` = the lookup-table
     model simulated along the reference SOC path from rest.

  Cell ``j`` has its own capacity ``Q_j = f_Q Q_ref``, start SOC ``soc0_j``, its
  own SOC path (coulomb counting with ``Q_j``), the table's parameters looked up at
  its own SOC, scaled by its factors (``R0 f_R0``, ``R1 f_R1``, ``tau1 f_tau1``,
  ``R2 f_R2``, ``tau2 f_tau2``; ``C = tau / R``; c0 unscaled) and simulated from
  rest; its voltage is that simulation **plus the measured residual** ``r(t)``.
  So a cell with all factors 1 and ``Q_j = Q_ref`` reproduces the measured voltage
  exactly, and every difference between cells is the injected one.

Spread (seeded, documented): ``rng = numpy.random.default_rng(seed)``; then, for
cells 1..n-1 in this order, ``z = rng.standard_normal((n - 1, 7))`` clipped to
``[-3, 3]``; columns ``capacity, r0, r1, tau1, r2, tau2, soc0``; factor
``f = 1 + sigma z`` (relative sigmas, :class:`CellSpread`, must be < 1/3 so that
every factor stays positive), ``soc0_j = initial_soc + sigma_soc0 z`` clipped to
[0, 1]. Defaults: capacity 2 %, R0 5 %, R1/R2 5 %, tau1/tau2 5 %, soc0 0.

Cells whose capacity is below ``Q_ref`` reach a lower SOC; no cut-off is applied
(the OCV continues linearly beyond its table).

The truth (every injected number) goes to ``<out>.truth.json`` (:func:`truth_path`).
"""

from __future__ import annotations

import errno
import json
import math
import os
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import can
import numpy as np
from cantools.database.can import Database

from ..analysis import (
    PARAM_KEYS,
    lookup_params,
    reference_capacity,
    reference_soc,
    rmse_mv,
    run_identification,
    run_soc,
    simulate_with_params,
    soc_lookup_table,
)
from ..can.dbc import load_project_db
from ..can.e2e import E2EStamper
from ..can.signals import SignalCodec
from ..core.ocv import OcvCurve
from ..data import CellRecording, check_charge_span, load_recording
from ..errors import DataError, UsageError
from ..jsonsafe import to_jsonable
from ..ocv_table import read_ocv_table
from ..samples import CELLS, ocv_table

__all__ = [
    "CellModel",
    "CellSpread",
    "CellTruth",
    "EncodeResult",
    "FrameArrays",
    "LOG_SUFFIXES",
    "PackTrace",
    "TRUTH_FORMAT",
    "build_pack",
    "cell_for_path",
    "draw_cell_truths",
    "encode_log",
    "frame_arrays",
    "identify_cell_model",
    "pack_voltages",
    "parse_spread",
    "resolve_cell_defaults",
    "truth_dict",
    "truth_path",
    "truths_from_json",
    "write_messages",
]

TRUTH_FORMAT = "bms-estimator encode-log truth 1"
#: Output formats (python-can writers chosen by suffix).
LOG_SUFFIXES = (".log", ".asc", ".blf")

_CURRENT_MSG = "PackMeasurement"
_VOLTAGE_MSG = "CellVoltages"
_TEMPERATURE_MSG = "CellTemperatures"


# --------------------------------------------------------------------- spread
@dataclass(frozen=True)
class CellSpread:
    """1-sigma cell-to-cell spread: relative for the factors, absolute SOC for ``soc0``."""

    capacity: float = 0.02
    r0: float = 0.05
    r1: float = 0.05
    tau1: float = 0.05
    r2: float = 0.05
    tau2: float = 0.05
    soc0: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"spread {f.name} must be a finite number >= 0, got {v!r}")
            if f.name != "soc0" and v >= 1.0 / 3.0:
                raise ValueError(f"spread {f.name}={v} too large: factors 1 + 3 sigma must stay positive (< 1/3)")

    def scaled(self, k: float) -> "CellSpread":
        return CellSpread(**{f.name: getattr(self, f.name) * k for f in fields(self)})


def parse_spread(text: str | None) -> CellSpread:
    """``--spread``: empty -> defaults; ``X`` -> every default sigma times X;
    ``key=value,...`` over the defaults (keys of :class:`CellSpread`, ``rc`` = r1, tau1, r2, tau2)."""
    base = CellSpread()
    if text is None or not text.strip():
        return base
    text = text.strip()
    try:
        return base.scaled(float(text))
    except ValueError:
        pass
    values = asdict(base)
    for part in text.split(","):
        if not part.strip():
            continue
        if "=" not in part:
            raise ValueError(f"--spread: {part!r} is not key=value (keys: {', '.join(values)}, rc)")
        key, _, val = (s.strip() for s in part.partition("="))
        try:
            num = float(val)
        except ValueError:
            raise ValueError(f"--spread: {key}={val!r} is not a number") from None
        keys = ("r1", "tau1", "r2", "tau2") if key == "rc" else (key,)
        for k in keys:
            if k not in values:
                raise ValueError(f"--spread: unknown key {k!r} (keys: {', '.join(values)}, rc)")
            values[k] = num
    return CellSpread(**values)


@dataclass(frozen=True)
class CellTruth:
    """What was injected into one cell."""

    index: int
    measured: bool  # True for cell 0: the measured voltage
    capacity_ah: float
    soc0: float
    capacity_factor: float = 1.0
    r0_factor: float = 1.0
    r1_factor: float = 1.0
    tau1_factor: float = 1.0
    r2_factor: float = 1.0
    tau2_factor: float = 1.0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "CellTruth":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


def draw_cell_truths(
    n_cells: int, capacity_ah: float, initial_soc: float, spread: CellSpread, seed: int
) -> list[CellTruth]:
    """Cell 0 = measured (all factors 1), cells 1.. drawn as the module docstring says."""
    if n_cells < 1:
        raise ValueError("n_cells must be >= 1")
    rng = np.random.default_rng(seed)
    z = np.clip(rng.standard_normal((n_cells - 1, 7)), -3.0, 3.0)
    sig = np.array([spread.capacity, spread.r0, spread.r1, spread.tau1, spread.r2, spread.tau2])
    f = 1.0 + z[:, :6] * sig
    soc0 = np.clip(initial_soc + spread.soc0 * z[:, 6], 0.0, 1.0)
    out = [CellTruth(0, True, float(capacity_ah), float(initial_soc))]
    for j in range(1, n_cells):
        fq, fr0, fr1, ft1, fr2, ft2 = (float(x) for x in f[j - 1])
        out.append(
            CellTruth(
                index=j,
                measured=False,
                capacity_ah=float(capacity_ah * fq),
                soc0=float(soc0[j - 1]),
                capacity_factor=fq,
                r0_factor=fr0,
                r1_factor=fr1,
                tau1_factor=ft1,
                r2_factor=fr2,
                tau2_factor=ft2,
            )
        )
    return out


# ---------------------------------------------------------------------- model
@dataclass
class CellModel:
    """The model identified on the measured cell (see the module docstring)."""

    ocv: OcvCurve
    dt_s: float
    capacity_stated_ah: float
    capacity_ah: float  # reference (effective) capacity Q_ref
    capacity_source: str
    initial_soc: float
    soc_table: dict[str, np.ndarray]
    soc: np.ndarray  # reference SOC path
    residual_v: np.ndarray  # measured - model
    rejections: int

    @property
    def sim_rmse_mv(self) -> float:
        return float(1e3 * np.sqrt(np.mean(self.residual_v**2)))


#: most cells in series the project DBC's cell multiplexer addresses
MAX_CELLS = 2000


def check_cells(n_cells: int) -> None:
    """``--cells`` within 1..``MAX_CELLS`` (a usage error otherwise)."""
    if not 1 <= n_cells <= MAX_CELLS:
        raise UsageError(f"--cells must be 1..{MAX_CELLS} (the DBC's multiplexer range), got {n_cells}")


def _check_uniform(rec: CellRecording) -> float:
    """The recording's sample step; a file too short, unevenly sampled or finer than the 10 ms frames is a
    :class:`DataError` (exit 3: the file's fault, not the command line's)."""
    t = rec.time_s
    if len(t) < 10:
        raise DataError(f"{rec.source}: only {len(t)} samples; encode-log needs at least 10")
    d = np.diff(t)
    dt = float(np.median(d))
    if not np.allclose(d, dt, rtol=0, atol=1e-6 * max(1.0, dt)):
        k = int(np.flatnonzero(np.abs(d - dt) > 1e-6 * max(1.0, dt))[0])
        raise DataError(f"{rec.source}: encode-log needs uniformly sampled data; a step of {float(d[k]):.6g} s at "
                        f"t = {float(t[k]):.6g} s (median {dt:.6g} s)")
    if dt < 0.01 - 1e-12:
        raise DataError(f"{rec.source}: sample step {dt:g} s is finer than the 10 ms current frames")
    return dt


def identify_cell_model(
    rec: CellRecording,
    ocv: OcvCurve,
    capacity_ah: float,
    *,
    initial_soc: float = 1.0,
    reference_capacity_ah: float | None = None,
) -> CellModel:
    """Identify the measured cell over the whole of ``rec`` (module docstring, steps 1-4)."""
    dt = _check_uniform(rec)
    i = np.asarray(rec.current_a, dtype=float)
    v = np.asarray(rec.voltage_v, dtype=float)
    if reference_capacity_ah is not None:
        q_ref, source = float(reference_capacity_ah), "given"
    else:
        q_ref, source = reference_capacity(i, v, dt, ocv, capacity_ah, initial_soc)
        if source == "stated":
            srun = run_soc(i, v, ocv, capacity_ah, initial_soc, dt)
            q_ref, source = float(srun.capacity_ah[-1]), "online SOC estimator"
    soc = reference_soc(i, dt, q_ref, initial_soc)
    run = run_identification(i, v, soc, ocv, capacity_ah, dt)
    table = soc_lookup_table(run)
    sim = simulate_with_params(i, soc, ocv, lookup_params(table, soc), dt)
    return CellModel(
        ocv=ocv,
        dt_s=dt,
        capacity_stated_ah=float(capacity_ah),
        capacity_ah=float(q_ref),
        capacity_source=source,
        initial_soc=float(initial_soc),
        soc_table=table,
        soc=soc,
        residual_v=v - sim,
        rejections=int(run.rejections),
    )


def pack_voltages(
    current_a: np.ndarray, measured_v: np.ndarray, model: CellModel, truths: list[CellTruth]
) -> np.ndarray:
    """Cell voltages ``(n, len(truths))``: measured cells get ``measured_v``, the others the
    scaled lookup-table model along their own SOC path plus ``model.residual_v``."""
    i = np.asarray(current_a, dtype=float)
    n = len(i)
    out = np.empty((n, len(truths)))
    sim_idx = [k for k, t in enumerate(truths) if not t.measured]
    for k, t in enumerate(truths):
        if t.measured:
            out[:, k] = measured_v
    if not sim_idx:
        return out
    ts = [truths[k] for k in sim_idx]
    m = len(ts)

    def col(name: str) -> np.ndarray:
        return np.array([getattr(t, name) for t in ts], dtype=float)

    ii = np.ascontiguousarray(np.broadcast_to(i[:, None], (n, m)))
    soc = reference_soc(ii, model.dt_s, col("capacity_ah"), col("soc0"))
    p = lookup_params(model.soc_table, soc)
    p["r0_ohm"] = p["r0_ohm"] * col("r0_factor")
    for j in (1, 2):
        r = p[f"r{j}_ohm"] * col(f"r{j}_factor")
        tau = p[f"tau{j}_s"] * col(f"tau{j}_factor")
        p[f"r{j}_ohm"], p[f"tau{j}_s"] = r, tau
        with np.errstate(divide="ignore", invalid="ignore"):
            p[f"c{j}_f"] = np.where(r > 0, tau / np.where(r > 0, r, 1.0), np.inf)
    v = simulate_with_params(ii, soc, model.ocv, p, model.dt_s)
    out[:, sim_idx] = v + np.asarray(model.residual_v, dtype=float)[:, None]
    return out


@dataclass
class PackTrace:
    """The pack at the recording's sample rate."""

    time_s: np.ndarray  # (n,) from 0
    dt_s: float
    current_a: np.ndarray  # (n,) pack = cell current, positive = charge
    cell_voltage_v: np.ndarray  # (n, N)
    temperature_c: np.ndarray | None  # (n,) every cell
    model: CellModel
    truths: list[CellTruth]
    spread: CellSpread
    seed: int
    source: str = ""
    ocv_source: str = ""

    @property
    def n_cells(self) -> int:
        return int(self.cell_voltage_v.shape[1])

    @property
    def duration_s(self) -> float:
        return float(len(self.current_a) * self.dt_s)


def build_pack(
    rec: CellRecording,
    n_cells: int,
    ocv: OcvCurve,
    capacity_ah: float,
    *,
    seed: int = 0,
    spread: CellSpread = CellSpread(),
    initial_soc: float = 1.0,
    reference_capacity_ah: float | None = None,
    duration_s: float | None = None,
    ocv_source: str = "",
) -> PackTrace:
    """Identify the measured cell on the whole ``rec`` (more data, a better model), cut
    everything to ``duration_s`` from the start, draw the spread and simulate the pack."""
    check_cells(n_cells)
    dt = _check_uniform(rec)
    model = identify_cell_model(
        rec, ocv, capacity_ah, initial_soc=initial_soc, reference_capacity_ah=reference_capacity_ah
    )
    cut = rec
    if duration_s is not None:
        if not (duration_s > 0):
            raise ValueError("duration must be positive")
        n = min(len(rec), max(10, int(math.floor(duration_s / dt + 1e-9))))
        cut = CellRecording(
            rec.time_s[:n], rec.current_a[:n], rec.voltage_v[:n],
            None if rec.temperature_c is None else rec.temperature_c[:n], rec.source,
        )
        model = replace(model, soc=model.soc[:n], residual_v=model.residual_v[:n])
    truths = draw_cell_truths(n_cells, model.capacity_ah, initial_soc, spread, seed)
    volts = pack_voltages(cut.current_a, cut.voltage_v, model, truths)
    return PackTrace(
        time_s=np.asarray(cut.time_s) - cut.time_s[0],
        dt_s=dt,
        current_a=np.array(cut.current_a, dtype=float),
        cell_voltage_v=volts,
        temperature_c=None if cut.temperature_c is None else np.array(cut.temperature_c, dtype=float),
        model=model,
        truths=truths,
        spread=spread,
        seed=seed,
        source=str(rec.source),
        ocv_source=ocv_source,
    )


# --------------------------------------------------------------------- frames
def _raw(sig, phys: np.ndarray) -> np.ndarray:
    """Physical -> raw int64: rounded, clamped to [minimum, maximum]; NaN -> NotAvailable."""
    return SignalCodec.from_signal(sig).raw(phys)


def _pack(db_msg, raws: dict[str, np.ndarray], n: int) -> np.ndarray:
    """OR the raw values into 64-bit little-endian payloads (Intel signals only)."""
    if db_msg.length != 8:
        raise ValueError(f"{db_msg.name}: only 8-byte frames are supported")
    out = np.zeros(n, dtype=np.uint64)
    for name, raw in raws.items():
        sig = db_msg.get_signal_by_name(name)
        if sig.byte_order != "little_endian":
            raise ValueError(f"{db_msg.name}.{name}: only little-endian (Intel) signals are supported")
        mask = np.uint64((1 << sig.length) - 1)
        r = np.broadcast_to(np.asarray(raw, dtype=np.int64), (n,)).astype(np.uint64)  # two's complement
        out |= (r & mask) << np.uint64(sig.start)
    return out


@dataclass
class FrameArrays:
    """A time-ordered frame stream as arrays (``t0_s`` + integer microseconds)."""

    t_us: np.ndarray  # int64, from t0_s
    arbitration_id: np.ndarray  # int64
    data: np.ndarray  # uint64, little-endian payload of 8 bytes
    t0_s: float = 0.0
    extended: dict[int, bool] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t_us.size)

    @property
    def timestamps(self) -> np.ndarray:
        return (self._t0_us + self.t_us) / 1e6

    @property
    def _t0_us(self) -> int:
        return int(round(self.t0_s * 1e6))

    @property
    def duration_s(self) -> float:
        return 0.0 if not len(self) else float((self.t_us[-1] - self.t_us[0]) / 1e6)

    def iter_messages(self, start: int = 0, stop: int | None = None, chunk: int = 65536,
                      shift_s: float = 0.0) -> Iterator[can.Message]:
        """``can.Message`` objects made lazily (``timestamp = t0_s + t_us/1e6 + shift_s``)."""
        stop = len(self) if stop is None else min(stop, len(self))
        t0 = self._t0_us + int(round(shift_s * 1e6))
        Message = can.Message
        for a in range(start, stop, chunk):
            b = min(stop, a + chunk)
            ts = ((t0 + self.t_us[a:b]) / 1e6).tolist()
            ids = self.arbitration_id[a:b].tolist()
            blob = self.data[a:b].astype("<u8").tobytes()
            ext = self.extended
            for k, (t, i) in enumerate(zip(ts, ids)):
                yield Message(
                    timestamp=t, arbitration_id=i, is_extended_id=ext.get(i, True), dlc=8,
                    data=blob[8 * k : 8 * k + 8], check=False,
                )


def frame_arrays(
    trace: PackTrace,
    *,
    db: Database | None = None,
    t0_s: float = 0.0,
    current_period_s: float = 0.01,
    voltage_period_s: float = 0.1,
    temperature_period_s: float = 1.0,
) -> FrameArrays:
    """Encode a :class:`PackTrace` as the frame stream of the module docstring."""
    db = db if db is not None else load_project_db()
    m_cur = db.get_message_by_name(_CURRENT_MSG)
    m_v = db.get_message_by_name(_VOLTAGE_MSG)
    m_t = db.get_message_by_name(_TEMPERATURE_MSG)
    n, N = trace.cell_voltage_v.shape
    dt_us = int(round(trace.dt_s * 1e6))
    total_us = n * dt_us
    cur_us, v_us, t_us_period = (int(round(p * 1e6)) for p in (current_period_s, voltage_period_s, temperature_period_s))

    # ---- current: charge-exact dithering of the held sample means
    mc = total_us // cur_us
    t_cur = np.arange(mc, dtype=np.int64) * cur_us
    sig_i = m_cur.get_signal_by_name("PackCurrent")
    unit_as = sig_i.scale * cur_us / 1e6  # A*s of one raw step held for one frame
    edges = np.arange(n + 1, dtype=np.int64) * dt_us
    cum = np.concatenate([[0.0], np.cumsum(trace.current_a * trace.dt_s)])  # A*s at sample edges
    q = np.interp(np.append(t_cur, total_us).astype(float), edges.astype(float), cum) / unit_as
    raw_i = np.diff(np.rint(q)).astype(np.int64)
    lo, hi = _raw(sig_i, np.array([sig_i.minimum]))[0], _raw(sig_i, np.array([sig_i.maximum]))[0]
    raw_i = np.clip(raw_i, lo, hi)
    k_cur = t_cur // dt_us
    pack_v = np.sum(trace.cell_voltage_v, axis=1)
    stamper = E2EStamper(db, "default")  # alive counters and CRC (module docstring)
    d_cur = stamper.stamp_rows(m_cur.frame_id, _pack(m_cur, {
        "PackCurrent": raw_i,
        "PackVoltage": _raw(m_cur.get_signal_by_name("PackVoltage"), pack_v[k_cur]),
        "CurrentInvalid": np.zeros(mc, np.int64),
        "VoltageInvalid": np.zeros(mc, np.int64),
    }, mc))

    # ---- cell voltages: ceil(N/3) frames per round, spread over the round
    def cell_frames(db_msg, prefix: str, per_frame: int, period_us: int, values: np.ndarray | None):
        n_fr = -(-N // per_frame)
        rounds = total_us // period_us
        offs = (np.arange(n_fr, dtype=np.int64) * period_us) // n_fr
        t = (np.arange(rounds, dtype=np.int64)[:, None] * period_us + offs[None, :]).reshape(-1)
        k = t // dt_us
        base = np.tile(np.arange(n_fr, dtype=np.int64) * per_frame, rounds)
        raws: dict[str, np.ndarray] = {"CellIndexBase": base}
        for j in range(per_frame):
            sig = db_msg.get_signal_by_name(f"{prefix}{j}")
            cell = base + j
            if values is None:
                phys = np.full(t.size, np.nan)
            elif values.ndim == 1:
                phys = values[k]
            else:
                phys = values[k, np.minimum(cell, N - 1)]
            phys = np.where(cell < N, phys, np.nan)
            raws[sig.name] = _raw(sig, phys)
        return t, stamper.stamp_rows(db_msg.frame_id, _pack(db_msg, raws, t.size))

    t_v, d_v = cell_frames(m_v, "CellVoltage", 3, v_us, trace.cell_voltage_v)
    t_t, d_t = cell_frames(m_t, "CellTemperature", 6, t_us_period, trace.temperature_c)

    t_all = np.concatenate([t_cur, t_v, t_t])
    ids = np.concatenate([
        np.full(t_cur.size, m_cur.frame_id, np.int64),
        np.full(t_v.size, m_v.frame_id, np.int64),
        np.full(t_t.size, m_t.frame_id, np.int64),
    ])
    data = np.concatenate([d_cur, d_v, d_t])
    order = np.argsort(t_all, kind="stable")  # equal times: current, voltages, temperatures
    return FrameArrays(
        t_us=t_all[order],
        arbitration_id=ids[order],
        data=data[order],
        t0_s=float(t0_s),
        extended={m.frame_id: m.is_extended_frame for m in (m_cur, m_v, m_t)},
    )


# ---------------------------------------------------------------------- files
def truth_path(out: str | Path) -> Path:
    """``OUT.log`` -> ``OUT.log.truth.json``."""
    return Path(str(out) + ".truth.json")


def _check_suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in LOG_SUFFIXES:
        raise ValueError(f"{path}: output must end in {', '.join(LOG_SUFFIXES)} (candump log, Vector ASC, Vector BLF)")
    return suffix


def write_messages(
    messages: Iterable[can.Message], path: str | Path, *, progress: Callable[[int], None] | None = None
) -> int:
    """Write frames with python-can's writer for the suffix (``can.Logger``); returns the count."""
    path = Path(path)
    _check_suffix(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    with can.Logger(str(path)) as writer:
        on = writer.on_message_received
        for msg in messages:
            on(msg)
            n += 1
            if progress is not None and not n & 0x3FFF:
                progress(n)
    if progress is not None:
        progress(n)
    return n


def cell_for_path(path: str | Path) -> str | None:
    """The shipped sample cell (a key of ``samples.CELLS``) whose name appears in ``path``."""
    norm = str(path).lower().replace("_", "-")
    hits = [c for c in CELLS if c in norm]
    return max(hits, key=len) if hits else None


def resolve_cell_defaults(
    data: str | Path, ocv: str | Path | None, capacity_ah: float | None
) -> tuple[OcvCurve, str, float]:
    """OCV curve, its source and the stated capacity; defaults from the shipped sample of the
    cell named in ``data``'s path. Raises ``ValueError`` when neither is available."""
    cell = cell_for_path(data)
    if (ocv is None or capacity_ah is None) and cell is None:
        missing = " and ".join(x for x, v in (("--ocv", ocv), ("--capacity-ah", capacity_ah)) if v is None)
        raise ValueError(
            f"{data}: no shipped cell ({', '.join(sorted(CELLS))}) in the file name, so {missing} "
            "must be given (OCV table from 'bms-estimator ocv', the cell's stated capacity)"
        )
    if ocv is None:
        ocv_path = ocv_table(cell)
    else:
        ocv_path = Path(ocv)
    curve = read_ocv_table(ocv_path)
    q = float(capacity_ah) if capacity_ah is not None else float(CELLS[cell][0])
    if not (math.isfinite(q) and q > 0):
        raise ValueError(f"capacity must be positive, got {q}")
    return curve, str(ocv_path), q


@dataclass
class EncodeResult:
    path: Path
    truth_path: Path
    frames: int
    duration_s: float
    truth: dict[str, Any]
    trace: PackTrace
    arrays: FrameArrays


def truth_dict(trace: PackTrace, fa: FrameArrays, *, out: str = "") -> dict[str, Any]:
    m = trace.model
    ref_table = {k: np.asarray(v).tolist() for k, v in m.soc_table.items()}
    q_ah = float(np.sum(trace.current_a) * trace.dt_s / 3600.0)
    soc_end = [float(t.soc0 + q_ah / t.capacity_ah) for t in trace.truths]
    p50 = lookup_params(m.soc_table, np.array([0.5]))
    cells = []
    v0 = trace.cell_voltage_v[:, 0]
    for t, se in zip(trace.truths, soc_end):
        d = asdict(t)
        d["soc_end"] = se
        d["r0_ohm_at_soc_50"] = float(p50["r0_ohm"][0] * t.r0_factor)
        d["voltage_rms_diff_to_cell0_mv"] = rmse_mv(trace.cell_voltage_v[:, t.index], v0)
        cells.append(d)
    return {
        "format": TRUTH_FORMAT,
        "log": out,
        "source": trace.source,
        "ocv": trace.ocv_source,
        "n_cells": trace.n_cells,
        "seed": trace.seed,
        "spread_sigma": asdict(trace.spread),
        "spread_rule": "rng = numpy.random.default_rng(seed); z = clip(rng.standard_normal((n_cells-1, 7)), -3, 3); "
                       "columns capacity,r0,r1,tau1,r2,tau2,soc0; factor = 1 + sigma*z; soc0 = initial_soc + sigma*z",
        "t0_s": fa.t0_s,
        "duration_s": trace.duration_s,
        "sample_period_s": trace.dt_s,
        "frames": len(fa),
        "frame_period_s": {_CURRENT_MSG: 0.01, _VOLTAGE_MSG: 0.1, _TEMPERATURE_MSG: 1.0},
        "reference": {
            "capacity_ah": m.capacity_ah,
            "capacity_source": m.capacity_source,
            "capacity_stated_ah": m.capacity_stated_ah,
            "initial_soc": m.initial_soc,
            "model_rmse_mv": m.sim_rmse_mv,
            "identifier_rejections": m.rejections,
            "residual": "measured minus lookup-table model of cell 0, added to every simulated cell",
        },
        "soc_table": ref_table,
        "param_keys": list(PARAM_KEYS),
        "cells": cells,
    }


def _warn_if_off_the_tables_temperature(rec: CellRecording, curve: OcvCurve, ocv_source: str) -> None:
    """Warn, as the other commands do, when the recording's median cell temperature is more than 5 K from the OCV
    table's: its cells are simulated on that table and its temperatures written to the log as read (a column in
    degF, 75 at 24 degC, went out as 75 degC cell temperatures without a word)."""
    from ..cli.common import SAME_AMBIENT_K, fahrenheit_hint
    from ..core.ocv import median_temperature_c

    if rec.temperature_c is None or curve.temperature_c is None:
        return
    median_c, table_c = median_temperature_c(rec.temperature_c), float(curve.temperature_c)
    if median_c is None or not math.isfinite(median_c) or abs(median_c - table_c) <= SAME_AMBIENT_K:
        return
    warnings.warn(f"{rec.source}: its median cell temperature {median_c:.1f} degC is {abs(median_c - table_c):.0f} K "
                  f"from the OCV table's {table_c:.1f} degC ({Path(ocv_source).name}): the cells are simulated on "
                  f"that table; give --ocv a table measured near {round(median_c)} degC"
                  f"{fahrenheit_hint(median_c, table_c, table_c)}", UserWarning, stacklevel=3)


def encode_log(
    data: str | Path,
    out: str | Path,
    n_cells: int,
    *,
    ocv: str | Path | None = None,
    capacity_ah: float | None = None,
    seed: int = 0,
    spread: CellSpread | None = None,
    initial_soc: float = 1.0,
    reference_capacity_ah: float | None = None,
    duration_s: float | None = None,
    t0_s: float = 0.0,
    progress: Callable[[int, int], None] | None = None,
) -> EncodeResult:
    """``bms-estimator encode-log`` as a function: writes ``out`` and ``truth_path(out)``.

    ``progress(written, total)`` is called while writing.
    """
    out = Path(out)
    _check_suffix(out)
    if not (0.0 <= initial_soc <= 1.0):
        raise ValueError(f"initial SOC must be in [0, 1], got {initial_soc}")
    data = Path(data)
    # said first: a missing file was told to give --ocv and --capacity-ah for it
    if not data.exists():
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(data))
    if data.is_dir():
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(data))
    curve, ocv_source, q = resolve_cell_defaults(data, ocv, capacity_ah)
    rec = load_recording(data)
    check_charge_span(rec, q, "--capacity-ah" if capacity_ah is not None else "the shipped cell's capacity")
    _warn_if_off_the_tables_temperature(rec, curve, ocv_source)
    trace = build_pack(
        rec, n_cells, curve, q, seed=seed, spread=spread if spread is not None else CellSpread(),
        initial_soc=initial_soc, reference_capacity_ah=reference_capacity_ah, duration_s=duration_s,
        ocv_source=ocv_source,
    )
    fa = frame_arrays(trace, t0_s=t0_s)
    total = len(fa)
    cb = (lambda k: progress(k, total)) if progress is not None else None
    written = write_messages(fa.iter_messages(), out, progress=cb)
    truth = truth_dict(trace, fa, out=str(out))
    tp = truth_path(out)
    tp.write_text(json.dumps(to_jsonable(truth), indent=2) + "\n")
    return EncodeResult(out, tp, written, trace.duration_s, truth, trace, fa)


def truths_from_json(truth: dict[str, Any]) -> list[CellTruth]:
    """The per-cell truth of a sidecar JSON (for checks against a decoded log)."""
    return [CellTruth.from_dict(c) for c in truth["cells"]]

