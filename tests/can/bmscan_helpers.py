"""Frame builders shared by the CAN tests (imported as a plain module: tests/can is on sys.path)."""

from __future__ import annotations

import can

from bms_estimator.can.e2e import E2EStamper
from bms_estimator.errors import MappingError

_STAMPERS: dict[int, tuple[object, E2EStamper | None]] = {}  # id(db) -> (db, its stamper): the db kept alive


def _stamper(db) -> E2EStamper | None:
    """The sender side of the preset's end-to-end checks for the project or the foxBMS DBC (None for others)."""
    if id(db) not in _STAMPERS:
        stamper = None
        for preset in ("default", "foxbms"):  # the project DBC, else foxBMS' (IVT-S message counters)
            try:
                stamper = E2EStamper(db, preset)
                break
            except MappingError:
                continue
        _STAMPERS[id(db)] = (db, stamper)
    return _STAMPERS[id(db)][1]


def frame(db, name: str, values: dict, t: float = 0.0, *, scaling: bool = True, strict: bool = True) -> can.Message:
    """A python-can message made with cantools ``encode_message`` (by name).

    Frames of the project and foxBMS DBCs carry their end-to-end checks as a sender makes them
    (:meth:`E2EStamper.encode`: the next alive counter value and the CRC, unless ``values``
    names them)."""
    m = db.get_message_by_name(name)
    stamper = _stamper(db)
    data = (stamper.encode(name, values, scaling=scaling, strict=strict) if stamper is not None
            else db.encode_message(name, values, scaling=scaling, strict=strict))
    return can.Message(timestamp=t, arbitration_id=m.frame_id, is_extended_id=m.is_extended_frame, data=data)


def fox_voltage_frame(db, mux: int, volts_mv: list[int], t: float = 0.0, invalid: tuple[int, ...] = ()) -> can.Message:
    """foxBMS AFE_CellVoltages frame for cells 4*mux .. 4*mux+3 (values in mV)."""
    values = {"AFE_CellVoltages_Mux": mux}
    for j in range(4):
        cell = 4 * mux + j
        values[f"CellVoltage_{cell:03d}"] = volts_mv[j]
        values[f"CellVoltage_{cell:03d}_invalidFlag"] = 1 if j in invalid else 0
    return frame(db, "AFE_CellVoltages", values, t)


def fox_current_frame(db, current_ma: int, t: float = 0.0, error: bool = False) -> can.Message:
    return frame(
        db,
        "CS_IsabellenhuetteIvtString0Curr",
        {
            "IVT_ID_Result_I": 0,
            "IVT_Result_I_System_Error": 0,
            "IVT_Result_I_Measurement_Error": 1 if error else 0,
            "IVT_Result_I_Channel_Error": 0,
            "IVT_Result_I_OCS": 0,
            "IVT_Result_I": current_ma,
        },
        t,
    )


def own_voltage_frame(db, base: int, volts: list[float], t: float = 0.0) -> can.Message:
    values = {"CellIndexBase": base}
    values.update({f"CellVoltage{j}": v for j, v in enumerate(volts)})
    return frame(db, "CellVoltages", values, t)


def own_current_frame(db, current_a: float, t: float = 0.0, voltage_v: float = 400.0, invalid: bool = False):
    return frame(
        db,
        "PackMeasurement",
        {
            "PackCurrent": current_a,
            "PackVoltage": voltage_v,
            "CurrentInvalid": 1 if invalid else 0,
            "VoltageInvalid": 0,
        },
        t,
    )
