"""Several independent drives as the cells of ONE vectorised estimator: the per-sample overhead shared.

A 96-cell update of :class:`~bms_estimator.core.soc.SocEstimator` costs mostly per-call
numpy overhead, not per-cell arithmetic, so ``S`` drives of ``n`` cells run side by side
as one ``S n``-cell estimator cost little more per sample than one drive. This is exact,
not an approximation, because every cell's estimate is a function of that cell's inputs
alone (the EKF shifts each cell's own identifier history:
``tests/core/test_soc_ekf.py::test_a_cell_estimates_the_same_alone_and_beside_other_cells``);
the results are checked bit for bit against the solo run in ``tests/fleet/test_fleet_stack.py``.

What a drive sees, step by step. :func:`~.estimate.estimate_drive` calls
``update(i, v, valid, T)`` for every sample ``k`` from its first valid current on (``i`` NaN
where the current is lost again: the estimator counts it with the current's running mean),
and before it leaves the estimator untouched (those rows repeat the fresh state). So drive
``d`` is a sequence of ``m_d`` *updates* at its samples ``u_d = {k : k >= k0_d}``, ``k0_d``
its first valid current, and the estimator's shared scalar counters (sample count, the LIF
ring's head and fill, the RLS error window's head) after ``j`` updates are the same for
every drive. The stack therefore runs step ``j`` as update ``j`` of every drive at once, the
current a per-cell vector (drive ``d``'s current on its cells; a Python float and a vector
filled with it give the same values), and maps back::

    row k of drive d  =  outputs after update  c_k - 1,   c_k = #{j in u_d : j <= k}
                         (the fresh estimator's values when c_k = 0)

A drive with fewer updates than the longest is fed, after its last, a filler (current 0,
no valid cell, no temperature); what its cells do then is never read: its outputs stop
at step ``m_d`` and its final state (``state_dict`` sliced to its cells, scalar counters
included) is taken right after update ``m_d``. The drives therefore must start from the
same state (all fresh: chained drives of a vehicle stay sequential, see :mod:`.drive`),
and the stacked estimator's fresh state must be the solo one repeated ``S`` times, which
is checked once per stack.

SOP/SOE/SOH (``batch --sox``): with ``make_sox`` given, each step's update is followed by the
stacked :class:`~bms_estimator.core.sox.SoxEstimator`'s, as in :func:`~.estimate.estimate_drive`,
its cells grouped per drive (:meth:`SoxEstimator.set_groups
<bms_estimator.core.sox.SoxEstimator.set_groups>`: the learnt-resistance refresh, the slow
cadence and the pack figures kept per drive). A drive's per-cell SOX outputs map back as the
estimator's (NaN before its first update, where the solo run has none), its pack figures are its
group's column of ``pack_outputs_by_group`` (the floats of its solo ``pack_outputs``), its final
state carries the SOX part under ``sox.`` (:func:`~bms_estimator.service.state.estimator_state`),
and its energy in and out is the change of its cells' SOX counters from the fresh state.

Drives of a one-cell pack (single-cell CSV recordings) are stacked too, as ``S`` groups of one
cell. A one-cell estimator's arithmetic is not a wider one's column: numpy sums a ``(K, 1)``
array's contiguous column pairwise and a ``(K, N)`` one row by row, and its dot kernels for one
cell add the products in another order than for several; each moved the last bits (two 1-cell
slices of the LG HG2 UDDS recording: from their 162nd update on). With groups of one cell the
three places where that happened take the one-cell arithmetic per cell: the RLS's regressor made
contiguous before ``phi' theta``, its ``P phi`` and ``phi' P phi`` cell-major
(``core.rls._one_cell_gain_terms``), and the SOE's sum over its SOC grid cell-major
(``core.soe.energy_left_wh``'s ``one_cell_sums``). Checked bit for bit with and without SOX
(``tests/fleet/test_fleet_stack.py``), and for every identification method and the ``c0`` SOC
method on 2,500 samples of two drives.

Anything unusual (an update that raises, a state that does not split by cells, a drive with a
time jump, where the estimator rests its cells alone) raises
:class:`StackError`; the caller then runs the drives one by one (the service's per-sample
error handling applies there).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..can.sampler import first_current, sample_current
from ..core.soc import SocEstimator
from ..core.sox import SoxEstimator
from ..service.state import SOX_PREFIX, estimator_state
from .estimate import ENERGY_COUNTERS, DriveEstimate, drive_getters, finish_estimate, sample_gaps
from .samples import SampleArrays

__all__ = ["StackError", "estimate_stacked"]


class StackError(RuntimeError):
    """The drives cannot run stacked (the caller runs them one by one)."""


#: a state field that is one value in a solo estimator and one per cell (its group's) in a stacked one
PER_GROUP = -1


def _cell_axes(solo: dict[str, np.ndarray], stacked: dict[str, np.ndarray], s: int) -> dict[str, int | None]:
    """Per state field, the axis that holds the cells (None: a scalar shared by all cells; ``PER_GROUP``:
    a scalar per drive); checks that the stacked fresh state is the solo fresh state repeated ``s`` times."""
    axes: dict[str, int | None] = {}
    if solo.keys() != stacked.keys():
        raise StackError("the stacked estimator's state has other fields than the solo one")
    for key, a in solo.items():
        a, b = np.asarray(a), np.asarray(stacked[key])
        if a.ndim == 0 and b.ndim == 1 and s > 1:
            ax: int | None = PER_GROUP
            want = np.full(b.shape, a)
        else:
            diff = [i for i in range(a.ndim) if a.shape[i] != b.shape[i]] if a.ndim == b.ndim else None
            if diff is None or len(diff) > 1 or (not diff and a.ndim and s > 1):
                raise StackError(f"state field {key!r} does not split by cells ({a.shape} alone, {b.shape} stacked)")
            ax = diff[0] if diff else None
            want = a if ax is None else np.concatenate([a] * s, axis=ax)
        if not np.array_equal(want, b, equal_nan=True):
            raise StackError(f"state field {key!r} of a fresh stacked estimator is not the solo one repeated")
        axes[key] = ax
    return axes


def _slice_state(state: dict[str, np.ndarray], axes: dict[str, int | None], cols: slice) -> dict[str, np.ndarray]:
    """One drive's state (its cells ``cols``) out of the stacked estimator's, in the solo estimator's form."""
    out = {}
    for key, v in state.items():
        ax = axes[key]
        v = np.asarray(v)
        if ax is None:
            out[key] = np.array(v, copy=True)
        elif ax == PER_GROUP:
            out[key] = np.array(v[cols][0], copy=True)
        else:
            idx = [slice(None)] * v.ndim
            idx[ax] = cols
            out[key] = np.array(v[tuple(idx)], copy=True)
    return out


def estimate_stacked(drives: list[SampleArrays], make_estimator: Callable[[int], SocEstimator],
                     make_sox: Callable[[int], SoxEstimator] | None = None,
                     n_parallel: int | None = None) -> list[DriveEstimate]:
    """Each drive's :func:`~.estimate.estimate_drive` result from a fresh ``make_estimator(n)`` (and a
    fresh ``make_sox(n)`` after it, when given), run stacked.

    ``make_estimator(n_cells)`` builds a fresh estimator of ``n_cells`` cells (the same
    configuration for every size), ``make_sox`` likewise. All drives must have the same number of
    cells and sample period. Raises :class:`StackError` when they cannot run stacked.
    ``n_parallel`` as :func:`~.estimate.estimate_drive`'s (None: the SOX part's, 1 without one).
    """
    if not drives:
        return []
    n = drives[0].n_cells
    if any(d.n_cells != n or d.period_s != drives[0].period_s for d in drives):
        raise StackError("stacked drives must have the same cells and sample period")
    if any(sample_gaps(d.t_s, d.period_s).any() for d in drives):  # rested over at its own step: run alone
        raise StackError("a drive has a time jump in its samples")
    s = len(drives)
    big = n * s
    solo = make_estimator(n)
    est = make_estimator(big)
    solo_sox = sox = None
    if make_sox is not None:
        solo_sox, sox = make_sox(n), make_sox(big)
    if n_parallel is None:
        n_parallel = sox.config.sop.n_parallel if sox is not None else 1
    if s > 1:
        if not hasattr(est.identifier, "set_groups"):
            raise StackError("the identifier cannot keep the drives apart")
        est.identifier.set_groups([n] * s)  # what the cells share is kept per drive, as in each drive alone
        if sox is not None:
            sox.set_groups([n] * s)  # likewise the SOX part's
    axes = _cell_axes(estimator_state(solo, solo_sox), estimator_state(est, sox), s)
    fresh_state = estimator_state(solo, solo_sox)

    steps = [np.arange(first_current(d.current_a, d.current_valid), len(d)) for d in drives]
    counts = [int(u.size) for u in steps]
    length = max(counts)
    # stacked inputs, row j = update j of every drive; after a drive's last update: the filler
    current = np.zeros((length, big))
    volts = np.full((length, big), np.nan)
    temps = np.full((length, big), np.nan)
    valid = np.zeros((length, big), dtype=bool)
    for d, (dr, u) in enumerate(zip(drives, steps)):
        cols, m = slice(d * n, (d + 1) * n), u.size
        current[:m, cols] = sample_current(dr.current_a, dr.current_valid, n_parallel)[u][:, None]
        volts[:m, cols] = dr.cell_voltage_v[u]
        temps[:m, cols] = dr.cell_temperature_c[u]
        valid[:m, cols] = dr.valid[u]

    getters, sox_keys = drive_getters(est, sox)
    # drive-major: store[key][d, 0] the fresh estimator's values, store[key][d, j + 1] the outputs after
    # update j. A drive whose every sample is an update (the usual drive) then has its rows as one
    # contiguous block, taken as it is; otherwise one fancy index picks them. (Rows the stacked
    # estimator writes as (S n,) vectors go in as (S, n); the values are the same.)
    store = {key: np.empty((s, length + 1, n)) for key, _ in getters}
    for key, get in getters:  # (the SOX outputs: NaN before the first update, as a scalar)
        store[key][:, 0] = np.broadcast_to(np.asarray(get(), dtype=float), (big,)).reshape(s, n)
    targets = [(store[key][:, 1:].transpose(1, 0, 2), get) for key, get in getters]  # (length, S, n) views
    # the pack figures: pack[key][d, 0] NaN (none before the first update), pack[key][d, j + 1] after update j
    pack = {key: np.full((s, length + 1), np.nan) for key in (sox.pack_output_keys if sox is not None else ())}
    ends: dict[int, list[int]] = {}
    for d, m in enumerate(counts):
        ends.setdefault(m, []).append(d)
    states: list[dict[str, np.ndarray] | None] = [None] * s
    for d in ends.get(0, []):
        states[d] = {k: np.array(v, copy=True) for k, v in fresh_state.items()}
    update = est.update
    if sox is not None:  # one drive alone is one pack: its pack_outputs, as a group of one
        pack_figures = sox.pack_outputs_by_group if s > 1 else (
            lambda: {key: np.array([value]) for key, value in sox.pack_outputs().items()})
    try:
        for j in range(length):
            update(current[j], volts[j], valid[j], temperature_c=temps[j])
            if sox is not None:
                sox.update(est, current[j], volts[j], valid[j])
                for key, figures in pack_figures().items():
                    pack[key][:, j + 1] = figures
            for out, get in targets:
                out[j] = get().reshape(s, n)
            done = ends.get(j + 1)
            if done:
                full = estimator_state(est, sox)
                for d in done:
                    states[d] = _slice_state(full, axes, slice(d * n, (d + 1) * n))
    except Exception as exc:  # noqa: BLE001 - one by one, the service's per-sample error handling applies
        raise StackError(f"a stacked update failed ({type(exc).__name__}: {exc})") from exc

    results = []
    for d, (dr, u) in enumerate(zip(drives, steps)):
        # c_k: updates done by sample k; row 0 of the drive's block is the fresh estimator's values
        c = np.zeros(len(dr), dtype=np.int64)
        c[u] = 1
        c = np.cumsum(c)
        every = counts[d] == len(dr)  # c_k = k + 1: rows 1..m as they are
        cells = {key: arr[d, 1:counts[d] + 1] if every else arr[d, :counts[d] + 1][c] for key, arr in store.items()}
        if sox is None:
            results.append(finish_estimate(dr, cells, states[d], 0))
            continue
        figures = {key: arr[d, 1:counts[d] + 1] if every else arr[d, :counts[d] + 1][c] for key, arr in pack.items()}
        energy = {key: states[d][SOX_PREFIX + key] - fresh_state[SOX_PREFIX + key] for key in ENERGY_COUNTERS}
        pack_energy = {key: solo_sox.pack_energy_wh(wh) for key, wh in energy.items()}
        results.append(finish_estimate(dr, cells, states[d], 0, sox_keys, energy, figures, pack_energy))
    return results

