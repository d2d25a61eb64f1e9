"""The SOP/SOE/SOH frames (issue 14): every figure round-trips through the project's DBC."""

import math

import numpy as np

from bms_estimator.can.dbc import load_db
from bms_estimator.can.encoder import StateEncoder
from bms_estimator.service.schema import CAN_PACK_SOX_SIGNALS


def _decode(db, frames):
    return {db.get_message_by_frame_id(f.arbitration_id).name: db.decode_message(f.arbitration_id, f.data)
            for f in frames}


def test_pack_sox_frames_round_trip_in_si_and_nan_is_not_available():
    db = load_db()
    enc = StateEncoder(db)
    values = {
        "i_discharge_max_2s_a": 120.4, "i_charge_max_2s_a": 40.0, "p_discharge_max_2s_w": 45_230.0,
        "p_charge_max_2s_w": 15_000.0, "i_discharge_max_10s_a": 100.0, "i_charge_max_10s_a": 35.5,
        "p_discharge_max_10s_w": 38_000.0, "p_charge_max_10s_w": 13_330.0, "i_discharge_max_30s_a": 80.0,
        "i_charge_max_30s_a": 30.0, "p_discharge_max_30s_w": 30_000.0, "p_charge_max_30s_w": 11_000.0,
        "energy_left_wh": 12_345.0, "energy_delivered_wh": -250.0, "time_to_empty_s": 5400.0,
        "time_to_full_s": math.inf, "soh_capacity_min": 0.912, "soh_resistance_max": 1.234,
        "capacity_ah_mean": 2.812, "energy_discharged_wh": 1_234_567.0,
    }
    frames = enc.encode_pack_sox(values, timestamp=1.0)
    assert {db.get_message_by_frame_id(f.arbitration_id).name for f in frames} == set(CAN_PACK_SOX_SIGNALS)
    d = _decode(db, frames)
    assert math.isclose(d["PackLimits2s"]["DischargeCurrentLimit"], 120.4, abs_tol=0.05)
    assert math.isclose(d["PackLimits10s"]["DischargePowerLimit"], 38.0, abs_tol=0.005)  # kW
    assert math.isclose(d["PackLimits30s"]["ChargePowerLimit"], 11.0, abs_tol=0.005)
    assert math.isclose(d["PackEnergy"]["EnergyLeft"], 12.345, abs_tol=5e-4)  # kWh
    assert math.isclose(d["PackEnergy"]["EnergyDelivered"], -0.25, abs_tol=5e-4)
    assert d["PackEnergy"]["TimeToEmpty"] == 90  # min
    assert d["PackEnergy"]["TimeToFull"] == 4094  # not charging: the top of the range
    assert math.isclose(d["PackHealth"]["SohCapacity"], 91.2, abs_tol=0.05)  # %
    assert math.isclose(d["PackHealth"]["SohResistance"], 123.4, abs_tol=0.05)
    assert math.isclose(d["PackHealth"]["CapacityMean"], 2.812, abs_tol=5e-4)
    assert math.isclose(d["PackHealth"]["EnergyDischarged"], 1234.567, abs_tol=5e-4)
    # NaN (an SOH not yet justified, a missing horizon) -> the signal's NotAvailable raw value
    raw = {db.get_message_by_frame_id(f.arbitration_id).name: db.decode_message(f.arbitration_id, f.data,
                                                                              decode_choices=False, scaling=False)
           for f in enc.encode_pack_sox({"soh_capacity_min": np.nan}, timestamp=1.0)}
    assert raw["PackHealth"]["SohCapacity"] == 1023
    assert raw["PackLimits10s"]["DischargeCurrentLimit"] == 65535
