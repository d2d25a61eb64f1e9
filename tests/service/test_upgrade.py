"""An upgrade of a running fleet: the state file, configuration and outputs an older version left behind.

The service resumes the state file an older version saved where its fields mean what they meant then
(``tests/service/test_daemon.py``, ``test_restart_resumes_from_saved_state``; the core's ``load_state_dict``
fills fields added since). Where a version changed what a field means, the file is set aside with one log
line saying why, never resumed as if nothing had changed.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from structlog.testing import capture_logs
from test_daemon import CAPACITY_AH, N, PACK, channel, make_cfg, ocv

from bms_estimator.core.soc import SocEstimator
from bms_estimator.service.daemon import Service
from bms_estimator.service.state import save_state


def _legacy_meta(fingerprint: str) -> dict:
    """The meta every version up to this one wrote (service/daemon.py ``_state_to_save``)."""
    return {"pack_id": PACK, "n_cells": N, "fingerprint": fingerprint, "t_s": 2399.0, "samples": 2399,
            "sample_period_s": 1.0, "capacity_ah": CAPACITY_AH}


def _not_used(logs: list[dict]) -> list[dict]:
    return [e for e in logs if e["event"] == "saved estimator state not used; starting fresh" and "reason" in e]


def test_a_parallel_packs_state_counted_at_the_whole_pack_current_is_set_aside_saying_why(tmp_path):
    """With ``estimator.sop.n_parallel = k`` each cell is now fed the pack current / k; versions before fed
    each the whole pack current, so their state holds an SOC counted k times too fast, resistances 1/k of
    the cell's and energy counters k times it (k = 2, measured on the LG la92 pack log: R0 20.5 against 44.8
    mOhm, 3.53 against 1.77 Wh). An upgraded service resumed that file (its fingerprint had no n_parallel)
    and kept the halved resistances for good. Now it is set aside, the log naming n_parallel."""
    ch = channel()
    one = make_cfg(tmp_path, ch)
    two = make_cfg(tmp_path, ch, estimator={"sop": {"n_parallel": 2}})
    est = SocEstimator(N, ocv(), CAPACITY_AH, 1.0, initial_soc=0.6, config=Service(one).soc_config)
    path = Path(two.state.path)
    save_state(path, est.state_dict(), _legacy_meta(Service(one).fingerprint))  # as an older version saved it

    svc = Service(two)
    with capture_logs() as logs:
        assert svc.restore() is False
    assert not path.exists() and len(list(tmp_path.glob("state.npz.foreign-*"))) == 1  # kept, not deleted
    (line,) = _not_used(logs)
    assert "estimator.sop.n_parallel" in line["reason"] and "whole pack current" in line["reason"]

    # the same file with one cell per series element (n_parallel = 1, the default) is resumed as before
    save_state(path, est.state_dict(), _legacy_meta(Service(one).fingerprint))
    assert Service(one).restore() is True


def test_a_state_of_another_n_parallel_is_set_aside_naming_both(tmp_path):
    """A state saved by this version with ``n_parallel = 2`` resumes with 2, and is set aside (naming both
    values) with 3: what it learnt is at another current per cell."""
    ch = channel()
    two = make_cfg(tmp_path, ch, estimator={"sop": {"n_parallel": 2}})
    three = make_cfg(tmp_path, ch, estimator={"sop": {"n_parallel": 3}})
    svc = Service(two)
    assert svc.restore() is False  # no file yet
    state, meta, saved_at = svc._state_to_save()
    assert meta["n_parallel"] == 2
    save_state(Path(two.state.path), state, meta, saved_at=saved_at)
    again = Service(two)
    assert again.restore() is True
    save_state(Path(two.state.path), state, meta, saved_at=saved_at)
    with capture_logs() as logs:
        assert Service(three).restore() is False
    (line,) = _not_used(logs)
    assert "estimator.sop.n_parallel 2" in line["reason"] and "configured 3" in line["reason"]


def _state_with_capacity(svc: Service, capacity_ah: float) -> dict:
    est = SocEstimator(N, svc.ocv, svc.cfg.pack.capacity_ah, 1.0, initial_soc=0.6, config=svc.soc_config)
    state = est.state_dict()
    state["capacity_ah"] = np.full(N, capacity_ah)
    return state


def test_a_capacity_an_earlier_version_clipped_from_the_ocv_tables_is_set_aside_saying_why(tmp_path):
    """A 50 Ah pack on the example configuration (``pack.ocv_csv`` unset: the built-in 3.0 Ah curve) was
    counted by versions before the count's start moved to ``pack.capacity_ah`` with the curve's 3.0 Ah, which
    the EKF's first step clipped to 0.6 x 50 = 30 Ah: their state file holds 30 Ah for every cell (measured:
    the LG la92 pack log through 80de115). The upgraded service resumed it, counted the SOC
    with 30 Ah and warned that pack.capacity_ah, which is right, was wrong for these cells. Now a file saved
    without the count's start in its meta, whose cells sit at the bound that start clips to, is set aside
    saying so (its SOP/SOE/SOH part resumed); one whose capacity has moved inside the bounds, or saved by this
    version, is resumed."""
    cfg = make_cfg(tmp_path, channel(), pack={"capacity_ah": 50.0, "ocv_csv": None})
    svc = Service(cfg)
    path = Path(cfg.state.path)
    meta = dict(_legacy_meta(svc.fingerprint), capacity_ah=50.0)
    save_state(path, _state_with_capacity(svc, 30.0), meta)
    with capture_logs() as logs:
        assert Service(cfg).restore() is False
    assert not path.exists() and len(list(tmp_path.glob("state.npz.foreign-*"))) == 1
    (line,) = _not_used(logs)
    assert "30 Ah" in line["reason"] and "pack.capacity_ah" in line["reason"] and "earlier version" in line["reason"]

    # its SOP/SOE/SOH part does not depend on the capacity the SOC was counted with: the commissioning R0
    # the resistance SOH is measured against and the energy counters are resumed, and said to be
    sox = svc._new_sox()
    sox.resistance.r0_commissioning_ohm[:] = 0.021
    sox.energy_discharged_wh[:] = 1234.5
    state = {**_state_with_capacity(svc, 30.0), **{f"sox.{k}": v for k, v in sox.state_dict().items()}}
    save_state(path, state, meta, saved_at=time.time() - 3 * 86400)  # parked three days
    upgraded = Service(cfg)
    with capture_logs() as logs:
        assert upgraded.restore() is False
    assert np.all(upgraded.estimator.capacity_ah == 50.0) and not np.isfinite(upgraded.estimator.soc).any()
    np.testing.assert_array_equal(upgraded.pipeline.sox.resistance.r0_commissioning_ohm, 0.021)
    np.testing.assert_array_equal(upgraded.pipeline.sox.energy_discharged_wh, 1234.5)
    assert [e for e in logs if e["event"].startswith("the SOP/SOE/SOH part of the state set aside is resumed")]
    state, _, _ = upgraded._state_to_save()  # the next save carries them on
    np.testing.assert_array_equal(state["sox.soh.r0_commissioning_ohm"], 0.021)
    for p in tmp_path.glob("state.npz.foreign-*"):
        p.unlink()

    # a capacity learnt inside the bounds since: resumed
    save_state(path, _state_with_capacity(svc, 41.0), meta)
    assert Service(cfg).restore() is True
    # this version's file at the bound (the stated capacity really wrong): resumed, the bound flag says so
    _, now_meta, _ = svc._state_to_save()
    save_state(path, _state_with_capacity(svc, 30.0), now_meta)
    resumed = Service(cfg)
    assert resumed.restore() is True and np.all(resumed.estimator.capacity_at_bound == -1)


def test_a_state_set_aside_is_not_said_to_be_restored_first(tmp_path):
    """The journal of a start whose state file is set aside by the service (another estimator configuration,
    an earlier version's file) said ``estimator state restored`` and, the next line, ``saved estimator state
    not used; starting fresh``. Reading the file is not restoring it: only the line that resumes says so."""
    cfg = make_cfg(tmp_path, channel())
    svc = Service(cfg)
    save_state(Path(cfg.state.path), _state_with_capacity(svc, CAPACITY_AH), _legacy_meta("0123456789abcdef"))
    with capture_logs() as logs:
        assert Service(cfg).restore() is False
    assert _not_used(logs)
    assert not [e["event"] for e in logs if "restored" in e["event"] or "resumed" in e["event"]]
    save_state(Path(cfg.state.path), _state_with_capacity(svc, CAPACITY_AH), _legacy_meta(svc.fingerprint))
    with capture_logs() as logs:
        assert Service(cfg).restore() is True
    assert [e["event"] for e in logs if "resumed" in e["event"]] == ["estimator resumed from saved state"]


def test_the_7_day_state_max_age_of_earlier_example_configurations_is_named_at_start(tmp_path):
    """The example configuration of earlier versions spelt out ``state.max_age_s = 604800.0`` (7 days, then
    the default) and said every key showed its default. The default is now 366 days (a parked month keeps
    the learnt capacity, the commissioning R0 and the energy counters), but a configuration copied from
    that example keeps 7 days: upgraded, a vehicle parked a fortnight still started fresh, with nothing to
    say the default had moved. That value is now named at start, with the new default."""
    with capture_logs() as logs:
        Service(make_cfg(tmp_path, channel(), state={"max_age_s": 604800.0}))
    (note,) = [e for e in logs if e.get("config_key") == "state.max_age_s"]
    assert note["log_level"] == "warning" and "366 days" in note["event"] and "7 days" in note["event"]
    for state in ({}, {"max_age_s": 30 * 86400.0}, {"max_age_s": None}):  # the default, a value of one's own
        with capture_logs() as logs:
            Service(make_cfg(tmp_path, channel(), state=state))
        assert not [e for e in logs if e.get("config_key") == "state.max_age_s"]


def test_the_dbc_note_says_the_receivers_of_the_output_frames_must_switch_with_it(tmp_path):
    """A 50 Ah pack upgraded to a version with the large-cell DBC is told at every start to set
    ``can.dbc = "large-cell"``, "the same frames": same ids and bits, but R0/R1/R2/C1/C2/CapacityMean at other
    scalings, so every node decoding the output frames with the project DBC reads R0 four times the value
    sent. The note now says the receivers must decode with that DBC too, naming its file (and back)."""
    def note(**kw) -> str:
        with capture_logs() as logs:
            Service(make_cfg(tmp_path, channel(), **kw))
        (one,) = [r for r in logs if r["log_level"] == "warning" and r.get("config_key") == "can.dbc"]
        return one["event"]

    big = note(pack={"capacity_ah": 50.0, "ocv_csv": None})
    assert "bms_estimator_large_cell.dbc" in big and "receiver" in big
    small = note(can={"dbc": "large-cell"})
    assert "bms_estimator.dbc" in small and "receiver" in small
