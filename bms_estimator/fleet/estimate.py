"""The service's estimator over :class:`~.samples.SampleArrays`: per-cell SOC and parameters of one drive, or a vehicle's drives chained.

Each sample takes the service's step (:meth:`bms_estimator.service.pipeline.Pipeline.tick`
without its outputs): ``SocEstimator.update(i, v, valid, T)`` when the current is valid and
finite, else no update; then the per-cell values the service's snapshot would carry are
written into row k of preallocated ``(K, N)`` arrays. The results are the service's: the
same estimator object, fed the same arguments sample by sample, in time order. What the
batch does not need per sample is left out: the snapshot object, its pack statistics and
status counters, the output hooks. Values that
are functions of others are computed once over the whole drive, with the snapshot's own
arithmetic: ``tau1_s = r1_ohm * c1_f``, ``tau2_s = r2_ohm * c2_f`` (elementwise, so bit
for bit the per-sample values); ``voltage_v`` and ``temperature_c`` are the samples'.

SOP/SOE/SOH (``batch --sox``): with a :class:`~bms_estimator.core.sox.SoxEstimator` given,
each update is followed by ``SoxEstimator.update(est, i, v, valid)``, as the pipeline's tick
does, and row k also holds the per-cell values of ``SoxEstimator.outputs`` the snapshot carries
(its keys: ``SoxEstimator.output_keys``, the service's MQTT cell keys); before the drive's first
update they are NaN (the snapshot has none yet). The pack figures are the snapshot's ``pack_sox``,
the same call: ``SoxEstimator.pack_outputs()`` once the SOX part has outputs, its keys
(``SoxEstimator.pack_output_keys``, the service's pack payload keys) as ``(K,)`` series in
``DriveEstimate.pack`` (NaN before the first update, where the snapshot's ``pack_sox`` is empty).
The drive's energy in and out per cell (the SOX counters' change over the drive) is
``DriveEstimate.energy_wh``; the pack's, ``SoxEstimator.pack_energy_wh`` of those (the rule of
the pack payload's ``energy_discharged_wh``), ``DriveEstimate.pack_energy_wh``.

A sample whose update raises is logged and counted (``tick_errors``) and its row stays
NaN, as the service's tick does (logged, no snapshot).

Gaps: a sample that does not follow the previous one (the sampler's grid re-anchored on a time
jump) rests the estimator over the hole first, as the service's pipeline does
(:func:`~bms_estimator.core.sox.rest_estimators`: the pack parked; the SOX part first when given).

Chaining: a vehicle's drives in time order, the estimator state carried from one drive to
the next as the service carries it across a restart: ``SocEstimator.state_dict()`` at the
end of a drive (:func:`~bms_estimator.service.state.estimator_state`: what the daemon saves,
with the SOX part under ``sox.``), ``load_state_dict`` into a fresh estimator for the next (what
the daemon's ``restore`` does; the SOX part by :func:`~bms_estimator.service.state.resume_sox`);
decoder and sampler start fresh, as after a restart.  The time between the drives is rested over
(:func:`rest_between_drives`) when both logs carry absolute times: frame times that are
epoch seconds (from 2000-01-01 on, :data:`EPOCH_MIN_S`), as candump ``.log`` and ``.blf``
files and ``.mf4`` files with their start time carry them; an ``.asc`` file (python-can
reads its times relative to the file's start) or a CSV recording (``time_s`` from 0) does
not, and then the state is carried without a rest, which the drive's result says.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import structlog

from ..can.sampler import first_current, sample_current
from ..core.soc import SocEstimator
from ..core.sox import SoxEstimator, rest_estimators
from ..gaps import gap_before_s
from ..service.schema import CELL_FIELDS
from ..service.state import estimator_state
from .samples import SampleArrays

__all__ = ["DriveEstimate", "EPOCH_MIN_S", "drive_getters", "estimate_drive", "carry_state", "finish_estimate",
           "output_getters", "rest_between_drives", "sample_gaps", "sox_getters"]

#: frame times from this on (2000-01-01 00:00 UTC) are epoch seconds: the log carries absolute times
EPOCH_MIN_S = 946_684_800.0

log = structlog.get_logger("bms.fleet")

#: the identifier's parameters a snapshot carries (PhysicalParams attributes)
PARAM_KEYS = ("r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "c0_v")


@dataclass(frozen=True, eq=False)
class DriveEstimate:
    """The snapshots of one drive as arrays: ``cells[key]`` is (K, N) for every per-cell key of the snapshot."""

    t_s: np.ndarray  # (K,)
    current_a: np.ndarray  # (K,)
    valid: np.ndarray  # (K, N) bool
    cells: dict[str, np.ndarray]
    state: dict[str, np.ndarray] = field(repr=False)  # estimator state at the end (for the next drive)
    tick_errors: int = 0  # samples whose update raised (their row is NaN)
    sox_keys: tuple[str, ...] = ()  # the SOX outputs among cells (batch --sox), in SoxEstimator.output_keys order
    # with SOX: (N,) Wh per cell that went out ("energy_discharged_wh") and in ("energy_charged_wh") in this drive
    energy_wh: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    # with SOX: (K,) per pack key of SoxEstimator.pack_outputs (the snapshot's pack_sox), in pack_output_keys order
    pack: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    # with SOX: the pack's Wh out ("energy_discharged_wh") and in ("energy_charged_wh") in this drive
    pack_energy_wh: dict[str, float] = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


def carry_state(make_estimator: Callable[[], SocEstimator], state: dict[str, np.ndarray] | None) -> SocEstimator:
    """A fresh estimator, resumed from ``state`` (a ``state_dict``) when given: the daemon's restore."""
    est = make_estimator()
    if state is not None:
        est.load_state_dict({k: np.array(v, copy=True) for k, v in state.items()})
    return est


def sample_gaps(t_s: np.ndarray, period_s: float) -> np.ndarray:
    """Seconds without samples before each sample (the sampler's :func:`~bms_estimator.gaps.gap_before_s`
    of its predecessor); 0 for the first."""
    gaps = np.zeros(t_s.shape[0])
    if t_s.shape[0] > 1:
        gaps[1:] = gap_before_s(t_s[1:], t_s[:-1], period_s)
    return gaps


def rest_between_drives(est: SocEstimator, previous_end_s: float | None, samples: SampleArrays,
                        sox: SoxEstimator | None = None) -> tuple[float | None, str]:
    """Rest a carried estimator (and its SOX part, when given) over the time between the previous drive's
    last sample (its end, ``previous_end_s``) and this drive's first period; returns ``(seconds rested or
    None, what was done)``."""
    if previous_end_s is None:
        return None, "not rested: the previous drive's end is unknown"
    start = float(samples.t_s[0]) - samples.period_s
    if not (previous_end_s >= EPOCH_MIN_S and start >= EPOCH_MIN_S):
        return None, "not rested: the logs carry no absolute times (state carried as if no time had passed)"
    gap = start - previous_end_s
    if gap < 0:
        return None, f"not rested: starts {-gap:.0f} s before the previous drive ended"
    if gap <= 0.5 * samples.period_s:
        return 0.0, "contiguous with the previous drive"
    rest_estimators(est, sox, gap)
    return gap, f"rested {gap:.0f} s since the previous drive (parked)"


def _estimator_fields(est: SocEstimator) -> list[tuple[str, str]]:
    """(key, attribute) of the further per-cell outputs the snapshot reads off the estimator (schema.CellField.estimator)."""
    taken = {"soc", "capacity_ah", "tau1_s", "tau2_s", "voltage_v", "temperature_c", *PARAM_KEYS}
    return [(f.key, f.estimator) for f in CELL_FIELDS
            if f.estimator is not None and f.key not in taken and hasattr(est, f.estimator)]


def output_getters(est: SocEstimator) -> list[tuple[str, Callable[[], np.ndarray]]]:
    """(key, call) per per-cell value the snapshot reads off the estimator after a step: soc, the
    identifier's parameters, capacity_ah and the further schema fields; each call returns the (N,) value now."""
    def param(name: str) -> Callable[[], np.ndarray]:
        return lambda: getattr(est.identifier.params, name)

    def attr(name: str) -> Callable[[], np.ndarray]:
        return lambda: getattr(est, name)

    return [("soc", attr("soc")), *((key, param(key)) for key in PARAM_KEYS), ("capacity_ah", attr("capacity_ah")),
            *((key, attr(name)) for key, name in _estimator_fields(est))]


def sox_getters(sox: SoxEstimator) -> list[tuple[str, Callable[[], np.ndarray | float]]]:
    """(key, call) per per-cell SOX output (:attr:`SoxEstimator.output_keys`); each call returns the (N,)
    value now, NaN before the first update (when the snapshot carries none)."""
    def out(key: str) -> Callable[[], np.ndarray | float]:
        return lambda: sox.outputs.get(key, math.nan)

    return [(key, out(key)) for key in sox.output_keys]


def drive_getters(est: SocEstimator, sox: SoxEstimator | None
                  ) -> tuple[list[tuple[str, Callable[[], np.ndarray | float]]], tuple[str, ...]]:
    """The (key, call) pairs a drive's outputs are read with (:func:`output_getters`, then the SOX
    outputs of :func:`sox_getters` when ``sox`` is given) and the SOX keys among them."""
    getters: list[tuple[str, Callable[[], np.ndarray | float]]] = list(output_getters(est))
    if sox is None:
        return getters, ()
    more = sox_getters(sox)
    return getters + more, tuple(key for key, _ in more)


#: the SOX energy counters (Wh out, Wh in) whose change over a drive is its energy
ENERGY_COUNTERS = ("energy_discharged_wh", "energy_charged_wh")


def finish_estimate(samples: SampleArrays, cells: dict[str, np.ndarray], state: dict[str, np.ndarray],
                    errors: int, sox_keys: tuple[str, ...] = (), energy_wh: dict[str, np.ndarray] | None = None,
                    pack: dict[str, np.ndarray] | None = None,
                    pack_energy_wh: dict[str, float] | None = None) -> DriveEstimate:
    """The drive's estimate from the per-step outputs ``cells`` ((K, N) each): the derived and input columns added."""
    with np.errstate(all="ignore"):
        cells["tau1_s"] = cells["r1_ohm"] * cells["c1_f"]
        cells["tau2_s"] = cells["r2_ohm"] * cells["c2_f"]
    cells["voltage_v"] = np.array(samples.cell_voltage_v, dtype=float, copy=True)
    cells["temperature_c"] = np.array(samples.cell_temperature_c, dtype=float, copy=True)
    return DriveEstimate(t_s=samples.t_s.copy(), current_a=samples.current_a.copy(), valid=samples.valid.copy(),
                         cells=cells, state=state, tick_errors=errors, sox_keys=sox_keys,
                         energy_wh=energy_wh or {}, pack=pack or {}, pack_energy_wh=pack_energy_wh or {})


def estimate_drive(samples: SampleArrays, estimator: SocEstimator, decoder=None, sampler=None,
                   sox: SoxEstimator | None = None, n_parallel: int | None = None) -> DriveEstimate:
    """Run ``estimator`` (and ``sox`` after it, when given) over every sample of one drive; row k of each
    output is the service's snapshot after sample k.

    ``n_parallel``: cells in parallel per series element, each fed the pack current / n_parallel, as the
    service (:class:`~bms_estimator.service.pipeline.Pipeline`); None: ``sox``'s ``sop.n_parallel`` (1 without).

    (``decoder``/``sampler`` are accepted for the callers of the snapshot-based version and not used.)
    """
    k = len(samples)
    est = estimator
    getters, sox_keys = drive_getters(est, sox)
    if sox is not None:
        energy0 = {key: np.array(getattr(sox, key), copy=True) for key in ENERGY_COUNTERS}
    store = {key: np.empty((k, samples.n_cells)) for key, _ in getters}  # every row is written below (NaN on error)
    targets = [(store[key], get) for key, get in getters]
    pack: dict[str, np.ndarray] = {}
    if sox is not None:  # the snapshot's pack_sox: pack_outputs() once the SOX part has outputs
        pack = {key: np.full(k, np.nan) for key in sox.pack_output_keys}
    pack_targets = list(pack.items())
    nan = math.nan
    # Python floats, as Sample carries them; NaN where not valid (counted with its running mean, as the service)
    if n_parallel is None:
        n_parallel = sox.config.sop.n_parallel if sox is not None else 1
    current = sample_current(samples.current_a, samples.current_valid, n_parallel).tolist()
    first = first_current(samples.current_a, samples.current_valid)
    volts, temps, valid = samples.cell_voltage_v, samples.cell_temperature_c, samples.valid
    update = est.update
    gaps = sample_gaps(samples.t_s, samples.period_s).tolist()
    errors = 0
    for i in range(k):
        try:
            if gaps[i]:
                rest_estimators(est, sox, gaps[i])
            if i >= first:  # as the service: fed from the first valid current on (can.sampler.first_current)
                c = current[i]
                update(c, volts[i], valid[i], temperature_c=temps[i])
                if sox is not None:
                    sox.update(est, c, volts[i], valid[i])
            for out, get in targets:
                out[i] = get()
            if pack_targets and sox.outputs:
                figures = sox.pack_outputs()
                for key, out in pack_targets:
                    out[i] = figures.get(key, nan)
        except Exception as exc:  # noqa: BLE001 - the service's tick logs, counts and goes on; so does the batch
            errors += 1
            for out in (*store.values(), *pack.values()):
                out[i] = np.nan
            if errors <= 5:
                log.error("estimator step failed", sample=i, t_s=float(samples.t_s[i]),
                          error=f"{type(exc).__name__}: {exc}", exc_info=exc)
    energy = pack_energy = None
    if sox is not None:
        energy = {key: np.asarray(getattr(sox, key), dtype=float) - energy0[key] for key in ENERGY_COUNTERS}
        pack_energy = {key: sox.pack_energy_wh(wh) for key, wh in energy.items()}
    return finish_estimate(samples, store, estimator_state(est, sox), errors, sox_keys, energy, pack, pack_energy)
