"""SoxEstimator.set_groups: packs side by side in one SOX part give each pack its own outputs, bit for bit.

Two synthetic packs of 2 and 3 cells (unequal groups: the slice-by-slice reductions of core.groups),
each its own pulse current with rests of up to 2 min (steps out of a minute's rest: the learnt
D-second resistance scores windows in both, at other samples), the 3-cell pack parked once for 10 min
(``rest`` of its cells only: its slow cadence restarts, the other pack's does not). Run alone
(one-pack path, the service's) and side by side as one 5-cell SOC estimator and SOX part.
"""

import numpy as np

from bms_estimator.core.ecm import simulate_ecm
from bms_estimator.core.soc import SocEstimator
from bms_estimator.core.sox import SoxEstimator
from tests.conftest import pulse_current
from tests.core.test_rest import PARAMS, Q_AH, _ocv

N = 1500
REST_AT, REST_S = 805, 600.0  # off the 10 s slow cadence (samples 0, 10, ...)
SIZES = (2, 3)


def _pack(seed: int, n_cells: int, soc0: float) -> tuple[np.ndarray, np.ndarray]:
    """(current (N,), cell voltages (N, n)): one simulated cell, the others a few mV and mOhm apart."""
    i = pulse_current(N, seed, amp_a=4.0)
    v = simulate_ecm(i, 1.0, PARAMS, _ocv().ocv, soc0=soc0, capacity_ah=Q_AH, output="mean").voltage_v
    rng = np.random.default_rng(seed)
    cells = v[:, None] + 0.002 * np.arange(n_cells) + 0.003 * np.arange(n_cells) * i[:, None] / 4.0
    return i, cells + 1e-3 * rng.standard_normal(cells.shape)


def _solo(i, v, rest: bool):
    n = v.shape[1]
    est, sox = SocEstimator(n, _ocv(), Q_AH, 1.0, initial_soc=0.9), SoxEstimator(n, 1.0)
    rows, packs = [], []
    for k in range(N):
        if rest and k == REST_AT:
            sox.rest(REST_S, est=est)
            est.rest(REST_S)
        est.update(float(i[k]), v[k])
        sox.update(est, float(i[k]), v[k])
        rows.append({key: a.copy() for key, a in sox.outputs.items()})
        packs.append(sox.pack_outputs())
    return rows, packs, sox.state_dict(), sox


def test_packs_side_by_side_give_each_pack_its_solo_sox_outputs():
    (ia, va), (ib, vb) = _pack(1, SIZES[0], 0.9), _pack(2, SIZES[1], 0.9)
    alone = [_solo(ia, va, rest=False), _solo(ib, vb, rest=True)]
    assert all(s.residual.windows_scored > 0 for *_, s in alone)  # dR learnt in both packs
    n = sum(SIZES)
    est, sox = SocEstimator(n, _ocv(), Q_AH, 1.0, initial_soc=0.9), SoxEstimator(n, 1.0)
    est.identifier.set_groups(SIZES)
    sox.set_groups(SIZES)
    cols = [slice(0, SIZES[0]), slice(SIZES[0], n)]
    parked = np.arange(n) >= SIZES[0]
    current = np.concatenate([np.repeat(ia[:, None], SIZES[0], 1), np.repeat(ib[:, None], SIZES[1], 1)], axis=1)
    volts = np.concatenate([va, vb], axis=1)
    for k in range(N):
        if k == REST_AT:
            sox.rest(REST_S, parked, est=est)
            est.rest(REST_S, parked)
        est.update(current[k], volts[k])
        sox.update(est, current[k], volts[k])
        figures = sox.pack_outputs_by_group()
        for g, (rows, packs, _, _) in enumerate(alone):
            assert rows[k].keys() == sox.outputs.keys()
            for key, a in rows[k].items():
                assert np.array_equal(a, sox.outputs[key][cols[g]], equal_nan=True), (k, g, key)
            assert packs[k].keys() == figures.keys()
            for key, value in packs[k].items():
                assert np.array_equal(value, figures[key][g], equal_nan=True), (k, g, key)
    state = sox.state_dict()
    for g, (_, _, solo_state, _) in enumerate(alone):
        for key, a in solo_state.items():
            b = state[key][..., cols[g]] if key not in ("x_v",) else state[key][cols[g]]
            assert np.array_equal(a, b, equal_nan=True), (g, key)


def test_one_pack_refuses_group_figures_and_a_used_part_refuses_groups():
    i, v = _pack(3, 2, 0.8)
    est, sox = SocEstimator(2, _ocv(), Q_AH, 1.0, initial_soc=0.8), SoxEstimator(2, 1.0)
    try:
        sox.pack_outputs_by_group()
    except ValueError as exc:
        assert "set_groups" in str(exc)
    else:
        raise AssertionError("no groups: pack_outputs_by_group must refuse")
    est.update(float(i[0]), v[0])
    sox.update(est, float(i[0]), v[0])
    try:
        sox.set_groups([1, 1])
    except ValueError as exc:
        assert "fresh" in str(exc)
    else:
        raise AssertionError("set_groups on a used SOX part must refuse")
