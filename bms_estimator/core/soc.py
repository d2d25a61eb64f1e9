"""SOC estimation with online ECM identification: an EKF (default) or the paper's OCV-bias compensation (N cells).

The paper's steps, per sample k and per cell::

    1. coulomb counting      soc_k = soc_{k-1} + i_{k-1} Ts / (3600 Q)
    2. overpotential         v_o = v - OCV(soc_k)
    3. identification        theta, c0 from the online identifier (LIF or ARX)
    4. bias averaging        c0_avg, c0_std over the last ``c0_window_s``
    5. compensation          if c0_std < ``c0_stable_v`` and |c0_avg| > OCV'(soc) * ``soc_error_threshold``:
                                 soc <- OCV^-1(OCV(soc) + c0_avg)
    6. bookkeeping           v_o history -= c0_avg and c0 -= c0_avg (the bias moves out of the
                             model into the SOC, or it would be corrected twice); restart the average

A c0 > 0 means the cell's voltage sits above what OCV(soc) explains with the
identified impedance, i.e. the true OCV is higher: the SOC estimate was low.

Those are ``soc_method="c0"``.  By default (``"ekf"``) steps 4.-6. are an extended
Kalman filter driven by the identified model (:mod:`bms_estimator.core.soc_ekf`): it
corrects the counted SOC every sample and learns the capacity as a state of its own,
and every SOC move shifts the identifier's history and c0 as in step 6; the anchor
line below is the c0 method's.

Capacity.  The capacity a user states (nominal) is not the one coulomb counting
needs (aged cell, rate and temperature effects).  Every time the bias average is
stable, the OCV-implied SOC ``s_ocv = OCV^-1(OCV(soc) + c0_avg)`` is an anchor
at the counted charge ``q_ah``; the effective capacity is the inverse slope of
the least-squares line ``s_ocv = s_0 + q_ah / Q`` over all anchors, used once
the anchors span ``capacity_min_span`` of the stated capacity and the fit is
good, within ``capacity_bounds`` of it.  It re-scales the coulomb count from
then on and is reported.  The same line also says where the SOC is now
(``s_0 + q_ah / Q``), but that mixes the OCV-model errors of every SOC the
anchors were taken at.  By default (``capacity_soc_update="none"``) a new
capacity only re-scales the count from then on.  ``"recount"`` counts again
from the last OCV correction, ``soc = soc_fix + (q_ah - q_fix) / Q``, and
``"line"`` moves to the line's SOC; either moves the OCV difference out of the
model as in step 6.

At a bound.  A capacity estimate that runs into ``capacity_bounds`` and stays
there says the stated capacity is wrong for the cell (a misconfigured pack, or
a cell far outside its rating): every SOC counted with it is unreliable.
:attr:`SocEstimator.capacity_at_bound` says so per cell: -1 at the low bound,
+1 at the high one, 0 inside.  The EKF clips its capacity to the bounds, so
there it is the capacity in use within ``CAPACITY_BOUND_TOL`` of a bound
(``Q <= lo Q_stated (1 + tol)`` or ``Q >= hi Q_stated (1 - tol)``).  The c0
method never takes a capacity outside the bounds: there it is the anchor
line's capacity ``1 / slope`` that sits at or beyond a bound, once the line
is a good fit (RMS residual below ``capacity_max_rmse``) and its anchors span
``capacity_min_span`` of the capacity the line implies (not of the stated one,
which a cell 5x smaller than stated can never span).  For both, a capacity in
use outside the bounds from the start (the OCV table's capacity, far from the
stated one) counts as at that bound.  Limitation, measured on a synthetic 3 Ah
cell stated as 15 Ah: the c0 method's anchors follow its count and the line
stays near 13 Ah, so its anchor line does not see that one (the EKF's capacity
reaches 9 Ah, the low bound, after 2 h of a 3 h drive).  The c0 method's
second signal does (its **voltage line**): every ``VOLTAGE_LINE_EVERY_S`` the
OCV the voltage implies, averaged over ``VOLTAGE_LINE_TAU_S`` with the current and
the counted charge (``v_m``, ``i_m``, ``q_m``: exponential averages, restarted by a
rest), ``s_v = OCV^-1(v_m - (R0 + R1 + R2) i_m)`` (the identified resistances,
not c0: with a wrong capacity the identifier folds the drift into c0 and the
resistances), is a point ``(q_m, s_v)`` of a second least-squares line whose
capacity ``capacity_voltage_ah`` is reported once the SOC the voltage moved
along it, ``(q_max - q_min) / Q_v``, reaches ``VOLTAGE_LINE_MIN_MOVE``.  That line
needs no stable c0 and no fit bound; it flags (``capacity_at_bound``) where the
stated capacity is more than ``STATED_CAPACITY_RATIO_MAX`` (2) times ``Q_v`` or
less than half of it, a wider rule than the bounds (0.6 / 1.4) because its
``Q_v`` reads the model's error under load as capacity too.  Measured with the
tables' capacities removed (counted with the stated one), ``Q_v / stated``: with
the cell's own capacity stated 0.70-0.97 (LG HG2 udds at 25, 0, -10 degC, 0 degC
us06, 25 degC mixed1, -10 degC la92; Panasonic 18650PF 25 degC us06 and la92;
lowest LG 0 degC udds), never flagged, stated 5x
the cell's 0.19-0.29 (flagged 2630-8990 s into the drives); synthetic 3 Ah cell
above: 2.92 Ah stated right, 2.71 Ah stated 15 Ah (flagged at 3710 s).

Hysteresis.  By default the OCV the cell shows is the mean curve plus
``h * H(soc)``, with ``H`` the OCV table's half charge-discharge gap and ``h``
in [-1, 1] Plett's one-state hysteresis (:mod:`bms_estimator.core.hysteresis`),
starting at -1 (after a discharge).  Without it a discharging cell's OCV bias
c0 sits near -H, and compensation reads that as a low SOC.  A C/20 gap wider
than ``hysteresis_max_v`` is a leg's start transient, so the estimator reads the
table with ``H`` capped there and each measured branch kept where its leg ran
longest: the discharge branch below 40 % SOC, the charge branch above 60 %
(:meth:`~bms_estimator.core.ocv.OcvCurve.with_half_gap_cap`).  Capped about the
mean instead, the discharge branch sat 35-70 mV high at 5-10 % SOC on the LG
HG2 tables and every deep discharge ended 2-3 % low.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Annotated, Literal, get_args

import numpy as np
from annotated_types import Ge, Gt, Interval

from .arrhenius import cell_temperature_ok
from .bounds import check_bounds
from .cells import all_cells, any_cell, cell_vector, clip, rest_arguments
from .hysteresis import HysteresisParams, HysteresisState
from .identifier import Identifier, IdentifierConfig
from .identifier_methods import make_identifier
from .ocv_surface import STATED_CAPACITY_RATIO_MAX, Ocv
from .soc_ekf import SOC_VARIANCE_MAX, SocEkf, SocEkfConfig

__all__ = ["SocConfig", "SocEstimator", "CAPACITY_BOUND_TOL", "CAPACITY_SOC_UPDATES", "REST_SOC_READINGS", "SOC_METHODS",
           "VOLTAGE_LINE_RATIO_MAX", "voltage_line_capacity_ah"]

#: How the OCV evidence corrects the counted SOC (``SocConfig.soc_method``).
SocMethod = Literal["ekf", "c0"]
SOC_METHODS = get_args(SocMethod)

#: What a new capacity estimate may do to the SOC now (``SocConfig.capacity_soc_update``).
CapacitySocUpdate = Literal["none", "recount", "line"]
CAPACITY_SOC_UPDATES = get_args(CapacitySocUpdate)

#: A capacity within this fraction of a ``capacity_bounds`` bound is at it (``SocEstimator.capacity_at_bound``):
#: the EKF's step takes in at most 1 % a sample, so a capacity held at a bound stays within it.
CAPACITY_BOUND_TOL = 0.01

#: The c0 method's voltage line (module docstring, "At a bound"): averaging time constant [s], the period of
#: its points [s], the SOC its points must move along it before its capacity counts, and the ratio of stated to
#: voltage-line capacity beyond which the stated capacity is flagged (the tables' check's, core.ocv_surface)
VOLTAGE_LINE_TAU_S = 600.0
VOLTAGE_LINE_EVERY_S = 10.0
VOLTAGE_LINE_MIN_MOVE = 0.3
VOLTAGE_LINE_RATIO_MAX = STATED_CAPACITY_RATIO_MAX

#: A cell's start temperature, at which the identifier's and the diffusion branch's priors are taken, is its
#: first valid reading, or the median of its first this many valid readings
#: (``SocConfig.prior_temperature_window_s``; update, "Start temperature")
PRIOR_TEMPERATURE_READINGS = 5
#: ... where that median is more than this from where the priors are [K]: a move the cell cannot have made
#: in the window (a cell soaking from a warm charge cools by 1-2 K/min), so one of the readings was not the cell's
PRIOR_TEMPERATURE_TOLERANCE_K = 5.0

#: How a relaxed cell's voltage after a long rest meets the count (``SocConfig.rest_soc_reading``).
RestSocReading = Literal["ocv", "fused"]
REST_SOC_READINGS = get_args(RestSocReading)


@dataclass(frozen=True)
class SocConfig:
    """SOC-side tuning; the defaults serve both cells in ../shared/data."""

    identifier: IdentifierConfig = field(default_factory=IdentifierConfig)
    # "ekf": an extended Kalman filter on SOC, a diffusion branch and the capacity, driven by the
    # identified parameters (core.soc_ekf); "c0": the paper's OCV-bias compensation above a threshold
    soc_method: SocMethod = "ekf"
    ekf: SocEkfConfig = field(default_factory=SocEkfConfig)
    # Count with the OCV table's own C/20 capacity (the scale SOC is defined on) where the
    # table carries one, interpolated by temperature; else with the stated capacity.
    capacity_from_ocv: bool = True
    default_temperature_c: float = 25.0  # a cell whose temperature is unknown
    soc_error_threshold: Annotated[float, Ge(0)] = 0.02  # compensate when c0 means more than this SOC error
    c0_window_s: Annotated[float, Gt(0)] = 120.0  # averaging window of c0
    c0_stable_v: Annotated[float, Ge(0)] = 0.010  # c0 is stable when its std over the window is below this
    estimate_capacity: bool = True  # learn the effective capacity (EKF: its dq state; c0: the anchor line below)
    capacity_min_span: Annotated[float, Ge(0)] = 0.5  # anchors must span this fraction of the stated capacity (short spans amplify OCV-model error)
    capacity_bounds: tuple[Annotated[float, Gt(0)], Annotated[float, Gt(0)]] = (0.6, 1.4)  # relative to the stated capacity
    capacity_max_rmse: Annotated[float, Ge(0)] = 0.03  # max RMS residual (SOC) of the anchor line fit
    # What a new capacity estimate does to the SOC now (SOC RMSE after 1 h from a 20 % start,
    # 14 measured drive cycles at 25 degC, worst file: none 1.93 %, recount 2.38 %, line 2.19 %):
    #   "none"     only the count from now on uses it (the paper has no more)
    #   "recount"  count again from the last OCV correction with the new capacity
    #   "line"     move to the capacity line's least-squares SOC; it mixes the OCV-model errors of
    #              every SOC the anchors were taken at, and on a synthetic 10 % capacity error it
    #              is the best of the three
    capacity_soc_update: CapacitySocUpdate = "none"
    reanchor_min_soc: Annotated[float, Ge(0)] = 0.005  # "recount"/"line" move the SOC only by more than this
    # One-state OCV hysteresis from the OCV table's hysteresis_v column (zero if it has none):
    # a cell that has been discharging sits on the discharge branch, H(soc) below the mean curve.
    # Read on the mean curve that reads as a 2-4 % low SOC on both cells in ../shared/data.
    hysteresis: bool = True
    hysteresis_rate: Annotated[float, Ge(0)] = 30.0  # 1/(SOC fraction): the state saturates after ~3/rate of throughput
    # cap on H(soc), the other branch moved to within 2 cap of the measured one (module docstring):
    # the C/20 gap near empty is the charge leg's start transient, near full the discharge leg's
    hysteresis_max_v: Annotated[float, Ge(0)] = 0.05
    # A rest without samples (SocEstimator.rest: the pack parked, the gateway asleep) at least this
    # long has relaxed the cell: its first sample after it, taken at rest, reads the SOC from the
    # voltage as an OCV.  (The LG HG2 and Panasonic rests move the reading 0.2-1.3 % SOC per doubling
    # after 300-600 s: scoring.py; 30 min leaves the diffusion branch at exp(-1800/1200) = 22 %.)
    rest_relaxation_s: Annotated[float, Interval(ge=60.0, le=86400.0)] = 1800.0
    rest_current_c: Annotated[float, Interval(ge=0.0, le=0.2)] = 0.02  # |i| below this C-rate is rest
    # ... and that first sample is read at up to this C-rate, its modelled ohmic drop taken out: a vehicle's
    # gateway wakes with the idle draw (a DC/DC converter, C/50-C/20 on a big pack's cell) on the bus, and
    # a rest reading held to rest_current_c never came.  At C/10 on the data's cells R0 i is 6-20 mV and the
    # RC branches, relaxed by the rest, build 0.1-0.3 mV within the first period; a 20 % R0 error reads
    # 0.2-0.8 % SOC, against a count that cannot see a charge while parked at all.
    rest_read_current_c: Annotated[float, Interval(ge=0.0, le=0.5)] = 0.1
    # How that reading meets the count (README "Across a gap"):
    #   "ocv"    it replaces the count, with the EKF's ocv_start_soc_sigma (a start from rest)
    #   "fused"  one EKF update with the count's grown variance; a reading more than
    #            rest_gate_sigma of its own sigmas away (a charge while parked) replaces it
    rest_soc_reading: RestSocReading = "ocv"
    rest_gate_sigma: Annotated[float, Gt(0)] = 3.0
    # A period whose current is unknown (NaN: the current frame lost, a sensor fault) is counted with
    # the current's running mean over this time constant, and the EKF's SOC variance grows by what
    # that guess may miss (SocEstimator.update, "A lost current")
    current_hold_s: Annotated[float, Gt(0)] = 60.0
    # A cell's start temperature (its priors' temperature) is its first valid reading, checked by its
    # first PRIOR_TEMPERATURE_READINGS valid readings, spread over this window
    # (SocEstimator.update, "Start temperature")
    prior_temperature_window_s: Annotated[float, Interval(ge=0.0, le=3600.0)] = 40.0

    def __post_init__(self) -> None:
        if self.soc_method not in SOC_METHODS:
            raise ValueError(f"soc_method must be one of {SOC_METHODS}, got {self.soc_method!r}")
        if self.rest_soc_reading not in REST_SOC_READINGS:
            raise ValueError(f"rest_soc_reading must be one of {REST_SOC_READINGS}, got {self.rest_soc_reading!r}")
        if self.capacity_soc_update not in CAPACITY_SOC_UPDATES:
            raise ValueError(f"capacity_soc_update must be one of {CAPACITY_SOC_UPDATES}, got {self.capacity_soc_update!r}")
        check_bounds(self)
        if not 0 < self.capacity_bounds[0] < self.capacity_bounds[1]:
            raise ValueError(f"capacity_bounds must be 0 < low < high, got {list(self.capacity_bounds)}")

    def with_(self, **changes) -> "SocConfig":
        return replace(self, **changes)

    def as_dict(self) -> dict:
        return asdict(self)


class SocEstimator:
    """SOC, 2-RC parameters, OCV bias and capacity of N cells, one sample per call.

    Args:
        n_cells: number of cells (1..2000 and more), all updated in one call.
        ocv: the cell's OCV: one :class:`~bms_estimator.core.ocv.OcvCurve`, or an
            ``OcvSurface`` (several tables interpolated by the cell temperature).
        capacity_ah: the stated (nominal) capacity, scalar or per cell.
        dt_s: sample period.
        initial_soc: per-cell start SOC; ``None`` (or NaN for a cell) reads it from the
            OCV at the first sample (valid when the pack starts from rest).

    Temperature.  ``update(..., temperature_c=...)`` gives each cell's temperature;
    the OCV, its slope and hysteresis are read on the tables interpolated at it, and
    the counting capacity is the table capacity there, ``Q(T) = Q_cell Q_table(T) /
    Q_table(T_ref)``.  SOC is the fraction of the C/20 throughput at the cell's
    temperature: a charge moves it by ``dq / Q(T)``; a temperature change alone
    moves the OCV under it, not the SOC.

    Capacity at a bound.  ``capacity_at_bound`` (int8 per cell): -1 when the capacity
    estimate sits at ``capacity_bounds[0]`` x the stated capacity, +1 at
    ``capacity_bounds[1]`` x, 0 inside (module docstring, "At a bound"): the stated
    capacity is wrong for that cell and its SOC unreliable.

    Starting hysteresis.  A cell started full came off a charge (the charge branch,
    h = +1), one started empty off a discharge (h = -1); anywhere else the branch is
    unknown and the mean curve (h = 0) is the least-error guess.
    """

    def __init__(
        self,
        n_cells: int,
        ocv: Ocv,
        capacity_ah: float | np.ndarray,
        dt_s: float = 1.0,
        *,
        initial_soc: float | np.ndarray | None = None,
        config: SocConfig = SocConfig(),
    ):
        self.n_cells = int(n_cells)
        # the table the estimator reads: with hysteresis, its half gap capped, each branch kept
        # where it is measured best (OcvCurve.with_half_gap_cap)
        capped = getattr(ocv, "with_half_gap_cap", None)
        self.ocv = capped(config.hysteresis_max_v) if config.hysteresis and capped is not None else ocv
        self.dt_s = float(dt_s)
        self.config = config
        self._t_aware = hasattr(self.ocv, "temperatures_c")
        # a cell's temperature until one is given: the tables' own default, else the config's
        self.temperature_c = np.full(self.n_cells, float(getattr(ocv, "default_temperature_c",
                                                                 config.default_temperature_c)))
        self.capacity_stated_ah = np.broadcast_to(np.asarray(capacity_ah, dtype=float), (self.n_cells,)).copy()
        if np.any(~np.isfinite(self.capacity_stated_ah)) or np.any(self.capacity_stated_ah <= 0):
            raise ValueError("capacity_ah must be positive and finite")
        # capacity at the tables' reference temperature (the count uses it times relative_capacity(T))
        self.capacity_ah = self.capacity_stated_ah.copy()
        q_table = self._table_capacity_ah() if config.capacity_from_ocv else None
        if q_table is not None:
            self.capacity_ah[:] = q_table
        self.capacity_initial_ah = self.capacity_ah.copy()
        lo, hi = config.capacity_bounds  # the capacity estimate's bounds, per cell
        self._capacity_lo_ah, self._capacity_hi_ah = lo * self.capacity_stated_ah, hi * self.capacity_stated_ah
        self._rel_q = np.ones(self.n_cells)
        self.capacity_estimated = np.zeros(self.n_cells, dtype=bool)
        # -1 / +1: the capacity estimate sits at its low / high bound (the stated capacity is wrong), 0: inside
        self.capacity_at_bound = self._bound_side(self.capacity_ah)
        self.identifier: Identifier = make_identifier(self.n_cells, self.dt_s, self.capacity_stated_ah, config.identifier)
        self.soc = np.full(self.n_cells, np.nan)
        if initial_soc is not None:
            self.soc = np.broadcast_to(np.asarray(initial_soc, dtype=float), (self.n_cells,)).copy()
        self._w = max(2, int(round(config.c0_window_s / self.dt_s)))
        self._c0_buf = np.zeros((self.n_cells, self._w))
        self._c0_head = 0
        self._c0_count = np.zeros(self.n_cells, dtype=np.int64)
        self._c0_sum = np.zeros(self.n_cells)  # running sums over the window (re-summed every window)
        self._c0_sq = np.zeros(self.n_cells)
        self._i_prev = np.zeros(self.n_cells)
        # the current's running mean and mean squared deviation from it (what a lost current is counted
        # with, and how far that may be off), and the periods lost in a row (update, "A lost current")
        self._i_hold = np.zeros(self.n_cells)
        self._i_dev2 = np.zeros(self.n_cells)
        self._n_lost = np.zeros(self.n_cells, dtype=np.int64)
        self._hold_a = min(1.0, self.dt_s / config.current_hold_s)
        self.charge_ah = np.zeros(self.n_cells)  # counted charge since start (positive = charged)
        # the same at the reference temperature (dq / relative capacity): the capacity line's abscissa
        self._charge_ref_ah = np.zeros(self.n_cells)
        # the SOC and counted charge at the last OCV correction (or the start): a new capacity
        # estimate recounts the SOC from there
        self._soc_fix = self.soc.copy()
        self._q_fix = np.zeros(self.n_cells)
        self.corrections = np.zeros(self.n_cells, dtype=np.int64)
        self.v_o = np.zeros(self.n_cells)
        # capacity anchors: weighted sums of (q, s) for the line s = s0 + q / Q
        self._cap = np.zeros((self.n_cells, 6))  # n, sq, ss, sqq, sqs, sss
        self._q_min = np.full(self.n_cells, np.inf)
        self._q_max = np.full(self.n_cells, -np.inf)
        # the c0 method's voltage line: its sums as _cap's, its charge span, the averages behind its points
        self._vline = np.zeros((self.n_cells, 6))
        self._vq_min = np.full(self.n_cells, np.inf)
        self._vq_max = np.full(self.n_cells, -np.inf)
        self._v_mean = np.zeros(self.n_cells)
        self._i_mean = np.zeros(self.n_cells)
        self._q_mean = np.zeros(self.n_cells)
        self._v_warm = np.zeros(self.n_cells, dtype=np.int64)  # samples averaged since the start or a rest
        self._log_keep = -self.dt_s / VOLTAGE_LINE_TAU_S  # log(1 - a) per sample
        self._v_sum = np.zeros(self.n_cells)  # the period's used samples: sums and counts
        self._i_sum = np.zeros(self.n_cells)
        self._n_sum = np.zeros(self.n_cells, dtype=np.int64)
        self._n_all = 0
        self._vline_every = max(int(round(VOLTAGE_LINE_EVERY_S / self.dt_s)), 1)
        self._vline_warm = int(round(VOLTAGE_LINE_TAU_S / self.dt_s))
        #: the voltage line's capacity [Ah at the tables' reference temperature] (c0 method; NaN until its
        #: points moved VOLTAGE_LINE_MIN_MOVE of SOC along it)
        self.capacity_voltage_ah = np.full(self.n_cells, np.nan)
        self.samples = 0
        # hysteresis state in [-1, 1]: -1 on the discharge branch, +1 on the charge branch.
        # The state recursion is core.hysteresis's (unit amplitude); the amplitude here is the
        # OCV table's H(soc), capped.
        self.hysteresis_state = np.zeros(self.n_cells)
        self._hyst = (
            HysteresisState(self.n_cells, self.capacity_ah,
                            HysteresisParams(m_v=1.0, m0_v=0.0, gamma=config.hysteresis_rate, h0=0.0), self.dt_s)
            if config.hysteresis and ocv.has_hysteresis else None  # H = 0 without the column: nothing to track
        )
        self._start_hysteresis(np.isfinite(self.soc))
        self.ekf = (SocEkf(self.n_cells, self.dt_s, self.capacity_ah, config.ekf)
                    if config.soc_method == "ekf" else None)
        self._slow_floor = self.ekf is not None and config.ekf.slow_branch_floor > 0.0
        self._take_slow_branch_floor()
        # cells whose next valid sample follows a rest longer than the relaxation (rest())
        self._rest_due = np.zeros(self.n_cells, dtype=bool)
        self._any_rest_due = False
        # samples in a row each cell has been at rest (update, "A park with the gateway awake"), and how many
        # make a relaxed rest
        self._rest_n = np.zeros(self.n_cells, dtype=np.int64)
        self._rest_every = max(int(round(config.rest_relaxation_s / self.dt_s)), 1)
        self._any_parked = False
        # the start temperature (update, "Start temperature"): a cell's first valid readings, how many,
        # the sample from which the next may be taken, and the temperature its priors are at (NaN: the reference)
        self._t_start = np.full((self.n_cells, PRIOR_TEMPERATURE_READINGS), np.nan)
        self._t_start_n = np.zeros(self.n_cells, dtype=np.int64)
        self._t_start_next = np.zeros(self.n_cells, dtype=np.int64)
        self._t_start_open = True
        self._t_start_every = max(1, int(round(config.prior_temperature_window_s
                                               / (PRIOR_TEMPERATURE_READINGS - 1) / self.dt_s)))
        self._t_prior = np.full(self.n_cells, np.nan)

    # ------------------------------------------------------------------ OCV at the cell temperature
    def _table_capacity_ah(self) -> float | None:
        """The OCV table's C/20 capacity at its reference temperature, if it carries one."""
        ocv = self.ocv
        if self._t_aware:
            q = ocv.capacity_ah(self.config.default_temperature_c)
            rel = ocv.relative_capacity(self.config.default_temperature_c)
            q = None if q is None else float(q) / float(rel)
        else:
            q = getattr(ocv, "capacity_discharge_ah", None)
        return float(q) if q is not None and np.isfinite(q) and q > 0 else None

    def _mean_ocv(self, soc: np.ndarray) -> np.ndarray:
        return self.ocv.ocv(soc, self.temperature_c) if self._t_aware else self.ocv.ocv(soc)

    def _half_gap(self, soc: np.ndarray) -> np.ndarray:
        h = self.ocv.hysteresis(soc, self.temperature_c) if self._t_aware else self.ocv.hysteresis(soc)
        return self._capped(h)

    def _capped(self, gap: np.ndarray) -> np.ndarray:
        """H capped at ``hysteresis_max_v`` (a no-op on a table from ``with_half_gap_cap``; it serves
        an OCV object without that method)."""
        return np.minimum(gap, self.config.hysteresis_max_v)

    def _on_branch(self, mean_v: np.ndarray, gap: np.ndarray) -> np.ndarray:
        """The mean OCV moved onto the hysteresis state's branch, ``mean + h H``; H kept for the EKF step."""
        self._h_gap = gap
        return mean_v + self.hysteresis_state * gap

    def _slope(self, soc: np.ndarray) -> np.ndarray:
        return self.ocv.docv_dsoc(soc, self.temperature_c) if self._t_aware else self.ocv.docv_dsoc(soc)

    def _soc_at(self, ocv_v: np.ndarray) -> np.ndarray:
        return self.ocv.soc_from_ocv(ocv_v, self.temperature_c) if self._t_aware else self.ocv.soc_from_ocv(ocv_v)

    def _ocv(self, soc: np.ndarray) -> np.ndarray:
        """The OCV the cell shows now: the mean curve plus the hysteresis state times H(soc)."""
        v = self._mean_ocv(soc)
        return self._on_branch(v, self._half_gap(soc)) if self._hyst is not None else v

    def _ocv_and_slope(self, soc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(self._ocv(soc), self._slope(soc))``: one table lookup for both on a single curve (the
        values bit for bit those of the two calls); on tables by temperature, the two calls."""
        if self._t_aware:
            return self._ocv(soc), self._slope(soc)
        v, slope, gap = self.ocv.ocv_slope_hysteresis(soc)
        return (self._on_branch(v, self._capped(gap)) if self._hyst is not None else v), slope

    def _start_hysteresis(self, cells: np.ndarray) -> None:
        if self._hyst is None or not any_cell(cells):
            return
        s = np.where(np.isfinite(self.soc), self.soc, 0.5)
        h0 = np.where(s >= 0.98, 1.0, np.where(s <= 0.02, -1.0, 0.0))
        self._hyst.h = np.where(cells, h0, self._hyst.h)
        self.hysteresis_state = self._hyst.h.copy()

    def set_soc(self, soc: float | np.ndarray, cells: np.ndarray | None = None,
                sigma: float | np.ndarray | None = None) -> None:
        """Set the SOC of some cells (all by default), as a user or a state file would.

        The count restarts there; the c0 average restarts, since it was learnt
        against the old SOC; the hysteresis branch is guessed again from the SOC
        (class docstring); the EKF's SOC sigma becomes ``sigma`` (default: its
        ``initial_soc_sigma``).
        """
        sel = np.ones(self.n_cells, dtype=bool) if cells is None else np.asarray(cells, dtype=bool)
        s = np.broadcast_to(np.asarray(soc, dtype=float), (self.n_cells,))
        self.soc = np.where(sel, s, self.soc)
        self._soc_fix = np.where(sel, self.soc, self._soc_fix)
        self._q_fix = np.where(sel, self._charge_ref_ah, self._q_fix)
        self._c0_count = np.where(sel, 0, self._c0_count)
        self._start_hysteresis(sel)
        if self.ekf is not None:
            self.ekf.set_soc_sigma(self.config.ekf.initial_soc_sigma if sigma is None else sigma, sel)

    @property
    def soc_sigma(self) -> np.ndarray:
        """1-sigma SOC uncertainty (the EKF's; NaN for the c0 method, which has none)."""
        if self.ekf is None:
            return np.full(self.n_cells, np.nan)
        return self.ekf.soc_sigma

    @property
    def counting_capacity_ah(self) -> np.ndarray:
        """The capacity the count uses now: the cell's, at its temperature."""
        return self.capacity_ah * self._rel_q

    # ------------------------------------------------------------------
    def update(
        self,
        current_a: float | np.ndarray,
        voltage_v: np.ndarray,
        valid: np.ndarray | None = None,
        temperature_c: float | np.ndarray | None = None,
    ) -> None:
        """One sample period: mean current over the period, the cell voltages and temperatures.

        A lost current.  A cell whose current is not finite this period (the current frame lost, a
        sensor fault) is counted with the current's running mean ``i_m`` (exponential, time constant
        ``current_hold_s``), its voltage is not read (the overpotential is unknown), and the EKF's
        SOC variance grows by what that guess may miss: ``s_i = sqrt(mean (i - i_m)^2)``, the running
        RMS deviation, taken as coherent over the loss, so after ``n`` lost periods the SOC's sigma
        has grown by ``s_i n Ts / (3600 Q)`` (the variance by ``(s_i Ts / (3600 Q))^2 (2n - 1)``
        each period).  When the current comes back the voltage corrects the count by that larger
        uncertainty.  Measured on 19 losses of 300 s in ten measured drive cycles (LG HG2 at 25 and
        0 degC, Panasonic at 25 degC, from a correct full start; README, Reliability): SOC RMSE over
        the 30 min after the loss 0.91 % mean, 0.62 % median, one over 2 % (4.5 %), against 2.21 /
        1.24 % and six over 2 % (up to 6.5 %) with the lost periods skipped; worse at 4 of the 19.
        At the loss's end the count was within its grown 1-sigma at all 19.

        Start temperature.  The identifier's prior resistances and the EKF's diffusion resistance
        start at the cell's temperature by their Arrhenius line (a cold cell has 2-4x a warm one's).
        That temperature is the cell's first valid reading.  Its next readings, to
        ``PRIOR_TEMPERATURE_READINGS`` (5) in all, ``prior_temperature_window_s / 4`` apart, check it:
        where their median so far is more than ``PRIOR_TEMPERATURE_TOLERANCE_K`` (5 K) from it, a move
        no cell makes in that time, the priors move to the median (the identifier's on a cell not yet
        identified).  Within it they stay at the first reading, the start's.  A gateway's first sample
        often has no temperature yet (slower or multiplexed frames), and a BMS may send its
        signal's floor (-40 degC) until its first measurement: taken from the first sample alone,
        the 25 degC prior or a -40 degC one stayed for the whole drive.  Measured on the LG 0 and
        -10 degC drive cycles from a correct start, SOC RMSE from 30 min (correct first reading /
        first reading missing / first reading -40 degC): see the README, Reliability.

        A park with the gateway awake.  A cell whose samples have been at rest (``|i| <=
        rest_current_c`` C) for ``rest_relaxation_s`` in a row has relaxed as over a :meth:`rest` of
        that length, and reads its SOC from the voltage the same way (``_read_after_rest``), again
        every ``rest_relaxation_s`` while the rest lasts; from the first reading on, until a larger
        current, the rest-level current no longer moves the hysteresis state (it is a sensor's offset,
        not charge moved; over the first ``rest_relaxation_s`` it moves it as before).  Without it only
        a sleeping gateway's park was read: an awake one counted a current sensor's offset ``i_0`` for
        the whole park, the SOC drifting by ``i_0 t / (3600 Q)`` (50 mA over 9 h: 15 % of a 3 Ah cell),
        and the filter, correcting that drift every sample through the SOC's correlation with the
        capacity, read it as a capacity error: on a synthetic 2.997 Ah cell parked 9 h with -50 mA of
        offset the capacity went to 3.54 Ah and the CC-CV charge after it ended 10 % low with a sigma of
        1.3 % (now 3.04 Ah and 0.2 %; tests/core/test_charge.py).  The time counts samples only (a log sparser than
        ``rest_relaxation_s`` gets its rests from :meth:`rest`); a drive cycle's stops are minutes.
        """
        n = self.n_cells
        i = cell_vector(current_a, n)
        v = cell_vector(voltage_v, n)
        i_ok = np.isfinite(i)
        if temperature_c is not None:
            self._take_temperature(cell_vector(temperature_c, n), i_ok)
        ok = np.isfinite(v)
        if valid is not None:
            ok &= np.asarray(valid, dtype=bool)
        i_use = self._hold_current(i, i_ok)
        unset = ~np.isfinite(self.soc)
        any_unset = any_cell(unset)
        read_now = None  # SOC read from this sample's voltage (none in the usual sample): not to be used a second time
        if any_unset:
            read_now = unset & ok & i_ok  # (not under a load it does not know)
            if any_cell(read_now):
                self._start_from_voltage(read_now, v, i)
        self._count_rest(i)
        if self._any_rest_due:
            read_rest = self._read_after_rest(i, v, ok)
            read_now = read_rest if read_now is None else read_now | read_rest
        # 1. coulomb counting (the previous sample's current moved the SOC to now)
        q_now = self.capacity_ah * self._rel_q if self._t_aware else self.capacity_ah  # (x 1.0 is x: no copy)
        dq = self._i_prev * (self.dt_s / 3600.0)
        dz = dq / q_now
        # (the SOC moved only if unset; None: every cell has one, the usual sample: no select needed below)
        have_soc = None if not any_unset else np.isfinite(self.soc)
        every_soc = have_soc is None or all_cells(have_soc)
        # a cell is never below empty or above full: clamping keeps a wrong capacity from running away
        counted = clip(self.soc + dz, 0.0, 1.0)
        self.soc = counted if every_soc else np.where(have_soc, counted, self.soc)
        self.charge_ah += dq
        self._charge_ref_ah += dq / self._rel_q if self._t_aware else dq
        i_prev = self._i_prev
        self._i_prev = i_use
        if self._hyst is not None:
            # Plett's one-state model (core.hysteresis): the state at this sample's start
            self._hyst.capacity_ah = q_now
            # (parked: a rest-level current is a sensor's offset, not charge moved; update, "A park ...")
            self.hysteresis_state = self._hyst.update(np.where(self._parked(), 0.0, i_use) if self._any_parked
                                                      else i_use)
        # 2. overpotential at the middle of the period (the voltage is a period mean)
        soc_mid = self.soc + i_use * (0.5 * self.dt_s / 3600.0) / q_now
        if not every_soc:
            soc_mid = np.where(have_soc, soc_mid, 0.5)
        ocv_v, slope_mid = self._ocv_and_slope(soc_mid)
        self.v_o = v - ocv_v
        use = ok & i_ok if have_soc is None else ok & i_ok & have_soc
        every_use = all_cells(use)
        # 3. identification (v_o itself when every cell is used: what the select gives; read only)
        self.identifier.update(i_use, self.v_o if every_use else np.where(use, self.v_o, np.nan), use)
        # 4.-6. the OCV evidence corrects the count
        if self.ekf is not None:
            # (gating the correction on an identified model, or on rest, was measured worse on the
            # 25 degC matrix, 40 against 47 of 56 runs within 2 %: the strong early evidence of a
            # wrong start is read through the prior impedance)
            # (no cell read now: the mask is use's, which holds have_soc where some cell has none)
            self._ekf_step(i_prev, i_use, dz, slope_mid, use if read_now is None else use & ~read_now)
        self._compensate(use)
        if self.ekf is None:
            self._voltage_line(i_use, v, use, every_use)
        self.samples += 1

    def _hold_current(self, i: np.ndarray, i_ok: np.ndarray) -> np.ndarray:
        """The current to count this period: ``i`` where known, else the running mean (``update``'s
        "A lost current", which also grows the EKF's SOC variance here); the running mean and
        deviation take in the known currents."""
        a = self._hold_a
        if all_cells(i_ok):  # the usual sample
            d = i - self._i_hold
            self._i_hold += a * d
            self._i_dev2 += a * (d * d - self._i_dev2)
            if any_cell(self._n_lost):
                self._n_lost[:] = 0
            return i.copy()  # (kept as the next period's current: not the caller's array)
        d = np.where(i_ok, i - self._i_hold, 0.0)
        self._i_hold = self._i_hold + a * d
        self._i_dev2 = np.where(i_ok, self._i_dev2 + a * (d * d - self._i_dev2), self._i_dev2)
        self._n_lost = np.where(i_ok, 0, self._n_lost + 1)
        lost = ~i_ok & np.isfinite(self.soc)
        if self.ekf is not None and any_cell(lost):
            q_now = self.capacity_ah * self._rel_q if self._t_aware else self.capacity_ah
            step = np.sqrt(self._i_dev2) * (self.dt_s / 3600.0) / q_now
            self.ekf.grow_soc_variance(step * step * (2.0 * self._n_lost - 1.0), lost)
        return np.where(i_ok, i, self._i_hold)

    def _take_temperature(self, t: np.ndarray, i_ok: np.ndarray) -> None:
        """The cells' temperatures this sample: the start temperature (update, "Start temperature"),
        :attr:`temperature_c` (a lost reading keeps the last), and with tables by temperature the
        relative capacity there.

        With one OCV table the SOC path does not read the temperature, but what runs on the estimator
        does (the SOP's temperature derating, the resistance SOH's Arrhenius step: ``core.sox``): a cell
        at 80 degC must not be derated as one at 25 degC because its pack has a single table."""
        if self._t_start_open:  # the priors follow the start temperature, with or without T-tables
            self._take_start_temperature(t, i_ok)
        self.temperature_c = np.where(np.isfinite(t), t, self.temperature_c)
        if self._t_aware:
            self._rel_q = np.asarray(self.ocv.relative_capacity(self.temperature_c), dtype=float)
        self._take_slow_branch_floor()

    def _take_slow_branch_floor(self) -> None:
        """Sets the EKF's floor on the slow branch (``ekf.slow_branch_floor``) at :attr:`temperature_c`:
        ``_r2_floor_ohm`` (the identifier's prior R2 at the cell temperature times the share) and
        ``_tau2_floor_s`` (the prior's tau2), read by :meth:`_rc_pairs`."""
        if not self._slow_floor:
            return
        r2, tau2 = self.identifier.prior_slow_branch(self.temperature_c, self.config.default_temperature_c)
        self._r2_floor_ohm = self.config.ekf.slow_branch_floor * r2
        self._tau2_floor_s = tau2

    def _take_start_temperature(self, t: np.ndarray, i_ok: np.ndarray) -> None:
        """A valid reading of a cell that has begun (a valid current, or an SOC) joins its start readings
        when due; the cell's priors move to their median where it is ``PRIOR_TEMPERATURE_TOLERANCE_K``
        from where they are (or they have none)."""
        k = PRIOR_TEMPERATURE_READINGS
        due = cell_temperature_ok(t) & (self._t_start_n < k) & (self.samples >= self._t_start_next)
        due &= i_ok | np.isfinite(self.soc)
        if not any_cell(due):
            return
        rows = np.flatnonzero(due)
        self._t_start[rows, self._t_start_n[rows]] = t[rows]
        self._t_start_n[rows] += 1
        self._t_start_next[rows] = self.samples + self._t_start_every
        self._t_start_open = any_cell(self._t_start_n < k)
        t_new = self._t_prior.copy()
        t_new[rows] = np.nanmedian(self._t_start[rows], axis=1)
        move = ~np.isfinite(self._t_prior) | (np.abs(t_new - self._t_prior) > PRIOR_TEMPERATURE_TOLERANCE_K)
        move &= due
        if not any_cell(move):
            return
        t_new = np.where(move, t_new, self._t_prior)
        reference_c = self.config.default_temperature_c
        self.identifier.take_prior_at(t_new, reference_c, move)
        if self.ekf is not None:
            self.ekf.take_diffusion_prior_at(t_new, self._t_prior, reference_c, move)
        self._t_prior = t_new

    def _start_from_voltage(self, cells: np.ndarray, v: np.ndarray, i: np.ndarray) -> None:
        """The start SOC of ``cells`` read from their voltage as an OCV; the count and the hysteresis
        branch start there, the EKF with the reading's uncertainty.

        At rest (a pack started from rest) the voltage is the OCV to the table's accuracy
        (``ocv_start_soc_sigma``).  Under load (a gateway started mid-drive without a state) it is
        not: the ohmic drop of the identifier's prior at the start temperature, ``R0 i``, the one
        part of the overpotential a single sample shows, is taken out, and what the RC branches and
        the diffusion branch may hold, up to ``(R1 + R2 + r_d) |i|`` of the priors, is added to the
        uncertainty as an SOC, ``sigma^2 = ocv_start_soc_sigma^2 + ((R1 + R2 + r_d) |i| / dOCV/dz)^2``,
        at most a uniform SOC's (``SOC_VARIANCE_MAX``)."""
        p = self.identifier.params
        loaded = cells & (np.abs(i) > self.config.rest_current_c * self.capacity_stated_ah)
        if any_cell(loaded):
            v = np.where(loaded, v - p.r0_ohm * i, v)
        self.soc = np.where(cells, np.clip(self._soc_at(np.where(cells, v, 3.7)), 0.0, 1.0), self.soc)
        self._soc_fix = np.where(cells, self.soc, self._soc_fix)
        self._q_fix = np.where(cells, self._charge_ref_ah, self._q_fix)
        self._start_hysteresis(cells)
        if self.ekf is not None:  # a reading, not a guess: the OCV's own uncertainty, and the load's
            sigma = np.full(self.n_cells, self.config.ekf.ocv_start_soc_sigma)
            if any_cell(loaded):
                slope = np.maximum(self._slope(np.where(cells, self.soc, 0.5)), 1e-3)
                unseen = (p.r1_ohm + p.r2_ohm + self.ekf.r_diffusion_ohm) * np.abs(i) / slope
                # (never less known than knowing nothing: a uniform SOC's sigma at most)
                sigma = np.where(loaded, np.minimum(np.hypot(sigma, unseen), np.sqrt(SOC_VARIANCE_MAX)), sigma)
            self.ekf.set_soc_sigma(sigma, cells)

    def _rc_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """The identified RC pairs the EKF runs, ``(r_ohm, tau_s)``, each ``(N, 2)``: a slow branch below
        the floor (``ekf.slow_branch_floor``) is the floor's."""
        p = self.identifier.params
        r = np.empty((self.n_cells, 2))  # (N, 2) pairs, filled column by column (np.stack's values)
        r[:, 0], r[:, 1] = p.r1_ohm, p.r2_ohm
        tau = np.empty((self.n_cells, 2))  # p.tau1_s, p.tau2_s, multiplied into place
        np.multiply(p.r1_ohm, p.c1_f, out=tau[:, 0])
        np.multiply(p.r2_ohm, p.c2_f, out=tau[:, 1])
        if self._slow_floor:
            low = p.r2_ohm < self._r2_floor_ohm
            if any_cell(low):
                r[:, 1] = np.where(low, self._r2_floor_ohm, r[:, 1])
                tau[:, 1] = np.where(low, self._tau2_floor_s, tau[:, 1])
        return r, tau

    def rest(self, gap_s: float, cells: np.ndarray | None = None) -> None:
        """``gap_s`` seconds without samples, the pack parked (zero current): what the model says
        happened to ``cells`` (a bool mask; all by default) meanwhile.  Cells not named are untouched;
        ``rest(0)`` changes nothing.

        * The period in progress when the samples stopped is counted (as the next :meth:`update`
          would have), then the current is zero: the count does not move over the gap.
        * The identified RC voltages and the diffusion voltage relax, ``v_j <- exp(-gap / tau_j) v_j``;
          the EKF's covariance is its ``predict`` at ``i = 0``, ``gap / Ts`` times, in closed form
          (:meth:`SocEkf.rest`): the SOC's variance grows by the filter's random walk,
          ``drift_sigma_per_h^2 gap / 3600``.
        * The hysteresis state is kept: it follows charge, not time.
        * A start temperature still being checked (:meth:`update`) is kept as it is: over the gap the
          temperature may really have moved.
        * The identifier's regressor window restarts (:meth:`Identifier.rest`: it refills before it
          learns again; theta, P and the guard's state kept); the c0 average restarts.
        * A rest of ``rest_relaxation_s`` or longer relaxed the cell: at its next valid sample, if that
          is at rest or near it (``|i| <= rest_read_current_c`` C: a gateway wakes with the vehicle's idle
          draw), the voltage less what is left of the modelled overpotential (the ohmic drop ``R0 i``, the
          RC and diffusion voltages the rest left) is read as an OCV on the hysteresis branch,
          ``OCV(z) + h H(z) = v - eta``, and
          replaces the count (``rest_soc_reading="ocv"``) or is fused with it (``"fused"``).  A
          charge while parked (the count cannot see it) is thus caught at that first sample.
        """
        gap, sel = rest_arguments(gap_s, cells, self.n_cells)
        if gap == 0.0 or not any_cell(sel):
            return
        # the last period before the gap, counted and predicted as update() would
        q_now = self.counting_capacity_ah
        dq = np.where(sel, self._i_prev * (self.dt_s / 3600.0), 0.0)
        dz = dq / q_now
        live = sel & np.isfinite(self.soc)
        self.soc = np.where(live, clip(self.soc + dz, 0.0, 1.0), self.soc)
        self.charge_ah = self.charge_ah + dq
        self._charge_ref_ah = self._charge_ref_ah + dq / self._rel_q
        r, tau = self._rc_pairs()
        if self.ekf is not None:
            self.ekf.predict(self._i_prev, dz, q_now, r, tau, live)
            self.ekf.rest(gap, q_now, tau, live)
        self._i_prev = np.where(sel, 0.0, self._i_prev)
        self._i_hold = np.where(sel, 0.0, self._i_hold)  # parked: a current lost next is held at zero
        self.identifier.rest(gap, sel)
        self._c0_count = np.where(sel, 0, self._c0_count)
        self._v_warm = np.where(sel, 0, self._v_warm)  # the voltage line's averages restart
        self._v_sum = np.where(sel, 0.0, self._v_sum)
        self._i_sum = np.where(sel, 0.0, self._i_sum)
        self._n_sum = np.where(sel, 0, self._n_sum + self._n_all)
        self._n_all = 0
        if self._t_start_open:
            # the start temperature's check ends for the cells that have one: over the gap their
            # temperatures may really have moved, and the priors stay at the start's
            k = PRIOR_TEMPERATURE_READINGS
            self._t_start_n = np.where(sel & (self._t_start_n > 0), k, self._t_start_n)
            self._t_start_open = any_cell(self._t_start_n < k)
        if gap >= self.config.rest_relaxation_s:
            self._rest_due = self._rest_due | live
            self._any_rest_due = any_cell(self._rest_due)

    def _count_rest(self, i: np.ndarray) -> None:
        """The seconds each cell's samples have been at rest, ``t_r <- t_r + Ts`` where ``|i| <=
        rest_current_c`` C, else 0; at ``rest_relaxation_s`` its next reading is due, as after a :meth:`rest`
        of that length, and the time restarts (:meth:`update`, "A park with the gateway awake")."""
        at_rest = np.abs(i) <= self.config.rest_current_c * self.capacity_stated_ah  # (a lost current: not)
        self._rest_n = np.where(at_rest, self._rest_n + 1, 0)
        due = at_rest & (self._rest_n % self._rest_every == 0)
        if any_cell(due):
            self._rest_due = self._rest_due | (due & np.isfinite(self.soc))
            self._any_rest_due = any_cell(self._rest_due)
        self._any_parked = any_cell(self._parked())

    def _parked(self) -> np.ndarray:
        """The cells whose samples have been at rest for ``rest_relaxation_s`` or more in a row."""
        return self._rest_n >= self._rest_every

    def _soc_on_branch(self, ocv_v: np.ndarray) -> np.ndarray:
        """The SOC whose OCV on the hysteresis state's branch is ``ocv_v``: ``OCV(z) + h H(z) = ocv_v``
        (the mean curve's inverse, then two fixed-point steps for ``h H``)."""
        z = self._soc_at(ocv_v)
        if self._hyst is not None:
            for _ in range(2):
                z = self._soc_at(ocv_v - self.hysteresis_state * self._half_gap(np.clip(z, 0.0, 1.0)))
        return np.clip(z, 0.0, 1.0)

    def _read_after_rest(self, i: np.ndarray, v: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """The first valid sample after a long rest (:meth:`rest`): the cells at rest read their SOC
        from the voltage; returns them (their voltage is not used a second time this sample)."""
        cfg = self.config
        due = self._rest_due & ok
        self._rest_due = self._rest_due & ~ok  # a cell without a valid sample yet waits for its first
        self._any_rest_due = any_cell(self._rest_due)
        near_rest = np.abs(i) <= cfg.rest_read_current_c * self.capacity_stated_ah
        read = due & np.isfinite(i) & near_rest & np.isfinite(self.soc)
        if not any_cell(read):
            return read
        i0 = np.where(read, i, 0.0)
        v_ok = np.where(read, v, 0.0)
        p = self.identifier.params
        if self.ekf is None:  # the c0 method tracks no RC voltage: the resistive drop only
            ocv_v = v_ok - p.r0_ohm * i0
        else:  # what is left of the modelled overpotential after the rest
            e = self.ekf
            eta = p.r0_ohm * i0 + e.v_rc[:, 0] + e.v_rc[:, 1]
            ocv_v = v_ok - (1.0 + e.overpotential_gain) * eta - e.v_diffusion
        old = self.soc
        replace_ = read
        if self.ekf is not None and cfg.rest_soc_reading == "fused":
            ocv_now = self._ocv(old)
            slope = self._slope(old)
            ec = cfg.ekf
            unsure = (1.0 - np.abs(self.hysteresis_state)) * self._h_gap if self._hyst is not None else 0.0
            r_v = ec.voltage_sigma_v**2 + (ec.ocv_table_sigma_soc * slope) ** 2 + np.square(unsure)
            d_soc, replace_ = self.ekf.read_at_rest(ocv_v - ocv_now, slope, r_v, read, cfg.rest_gate_sigma)
            self.soc = np.where(read & ~replace_, clip(old + d_soc, 0.0, 1.0), self.soc)
        if any_cell(replace_):
            self.soc = np.where(replace_, self._soc_on_branch(ocv_v), self.soc)
            if self.ekf is not None:
                self.ekf.set_soc_sigma(cfg.ekf.ocv_start_soc_sigma, replace_)
        self._soc_fix = np.where(read, self.soc, self._soc_fix)
        self._q_fix = np.where(read, self._charge_ref_ah, self._q_fix)
        # the OCV the identifier saw moves with the SOC (as every EKF or c0 move does)
        shift = np.where(read, self._ocv(self.soc) - self._ocv(old), 0.0)
        if any_cell(shift):
            self.identifier.shift_bias(shift)
        return read

    def _ekf_step(self, i_prev: np.ndarray, i_now: np.ndarray, dz: np.ndarray, slope: np.ndarray,
                  use: np.ndarray) -> None:
        """Steps 4.-6. by the EKF; ``slope`` is dOCV/dSOC at the period's middle SOC."""
        p = self.identifier.params
        r, tau = self._rc_pairs()
        live = np.isfinite(self.soc)
        self.ekf.predict(i_prev, dz, self.capacity_ah * self._rel_q if self._t_aware else self.capacity_ah, r, tau, live)
        overpotential = p.r0_ohm * i_now + self.ekf.v_rc[:, 0] + self.ekf.v_rc[:, 1]  # the identified model's
        identified = self.identifier.identified
        if any_cell(self.identifier.newly_identified):  # the prediction g corrected is gone: g restarts
            self.ekf.restart_gain(self.identifier.newly_identified)
        innovation = self.v_o - ((1.0 + self.ekf.overpotential_gain) * overpotential + self.ekf.v_diffusion)
        unsure = (1.0 - np.abs(self.hysteresis_state)) * self._h_gap if self._hyst is not None else 0.0
        ec = self.config.ekf
        rho = (ec.overpotential_sigma if all_cells(identified)  # (the usual sample: the select's one value)
               else np.where(identified, ec.overpotential_sigma, ec.overpotential_sigma_prior))
        d_soc, d_q = self.ekf.correct(innovation, slope, cell_vector(unsure, self.n_cells), use,
                                      rho * np.abs(overpotential), overpotential)
        if self.config.estimate_capacity:
            self.capacity_ah = clip(self.capacity_ah * (1.0 + d_q), self._capacity_lo_ah, self._capacity_hi_ah)
            self.capacity_at_bound = self._bound_side(self.capacity_ah)
            self.capacity_estimated |= self.ekf.capacity_variance < (0.5 * self.config.ekf.capacity_sigma) ** 2
        self.soc = clip(self.soc + d_soc, 0.0, 1.0)
        # The OCV the identifier saw moves with the SOC, as in a c0 compensation: its history and
        # c0 shift with every EKF move, cell by cell.  (Shifting only once the pack's largest
        # pending move reached a millivolt saved a fifth of the update but made a cell's estimate
        # depend on the cells beside it: single matrix runs moved by up to 1 % SOC with the
        # grouping of files.  Shifted every sample, a cell's results are the same alone or in any
        # pack, which the batch's stacking of drives and the matrix rely on.)
        shift = slope * d_soc
        if any_cell(shift):
            self.identifier.shift_bias(shift)

    def _compensate(self, use: np.ndarray) -> None:
        if self.ekf is not None:
            return  # the EKF corrects the SOC and the capacity every sample; c0 is the identifier's
        cfg = self.config
        ident = self.identifier
        # only fresh, accepted estimates count: a theta frozen by the admissibility
        # guard has a constant c0 that would look perfectly 'stable'
        learn = use & ident.accepted
        h = self._c0_head
        old = self._c0_buf[:, h].copy()  # a copy: the slot is overwritten next
        new = np.where(learn, ident.c0_v, old)
        self._c0_buf[:, h] = new
        self._c0_head = (h + 1) % self._w
        if self._c0_head == 0:  # exact re-sum once per window: no drift of the running sums
            self._c0_sum = self._c0_buf.sum(axis=1)
            self._c0_sq = np.einsum("nw,nw->n", self._c0_buf, self._c0_buf)
        else:
            self._c0_sum += new - old
            self._c0_sq += new * new - old * old
        self._c0_count = np.where(learn, self._c0_count + 1, self._c0_count)
        full = self._c0_count >= self._w
        if not any_cell(full):
            return
        c0_avg = self._c0_sum / self._w
        c0_std = np.sqrt(np.maximum(self._c0_sq / self._w - c0_avg * c0_avg, 0.0))
        stable = full & (c0_std < cfg.c0_stable_v) & np.isfinite(c0_avg)
        if not any_cell(stable):
            return
        # SOC whose OCV is c0_avg above the one now: OCV^-1(OCV(soc) + c0_avg).  The hysteresis
        # term h H(soc) is on both sides (read at the SOC now), so the mean curve gives it
        soc_ocv = self._soc_at(self._mean_ocv(self.soc) + c0_avg)
        if cfg.estimate_capacity:
            self._capacity_anchor(stable, soc_ocv)
        slope = self._slope(self.soc)
        fire = stable & (np.abs(c0_avg) > slope * cfg.soc_error_threshold)
        if any_cell(fire):
            self.soc = np.where(fire, np.clip(soc_ocv, 0.0, 1.0), self.soc)
            self._soc_fix = np.where(fire, self.soc, self._soc_fix)
            self._q_fix = np.where(fire, self._charge_ref_ah, self._q_fix)
            ident.shift_bias(c0_avg, fire)
            self._c0_count = np.where(fire, 0, self._c0_count)
            self._shift_c0_window(np.where(fire, c0_avg, 0.0))
            self.corrections += fire

    def _shift_c0_window(self, d: np.ndarray) -> None:
        """Subtract a per-cell constant from every c0 in the window (and its running sums)."""
        w = self._w
        self._c0_sq += -2.0 * d * self._c0_sum + w * d * d
        self._c0_sum -= w * d
        rows = np.flatnonzero(d)  # usually a few cells: do not sweep the whole (N, window) buffer
        if rows.size:
            self._c0_buf[rows] -= d[rows, None]

    def _capacity_anchor(self, sel: np.ndarray, soc_ocv: np.ndarray) -> None:
        cfg = self.config
        q = self._charge_ref_ah
        s = soc_ocv
        add = np.stack([np.ones_like(q), q, s, q * q, q * s, s * s], axis=1)
        self._cap += np.where(sel[:, None], add, 0.0)
        self._q_min = np.where(sel, np.minimum(self._q_min, q), self._q_min)
        self._q_max = np.where(sel, np.maximum(self._q_max, q), self._q_max)
        span = self._q_max - self._q_min
        cand = sel & (span >= cfg.capacity_min_span * self.capacity_stated_ah)
        slope, q_est, fits = self._capacity_line()
        if not any_cell(cand):
            self.capacity_at_bound = self._capacity_side_c0(q_est, fits)
            return
        n, sq, ss = self._cap[:, 0], self._cap[:, 1], self._cap[:, 2]
        lo, hi = cfg.capacity_bounds
        good = (
            cand
            & fits
            & (q_est > lo * self.capacity_stated_ah)
            & (q_est < hi * self.capacity_stated_ah)
        )
        self.capacity_ah = np.where(good, q_est, self.capacity_ah)
        self.capacity_estimated |= good
        self.capacity_at_bound = self._capacity_side_c0(q_est, fits)
        if cfg.capacity_soc_update == "recount":
            target = self._soc_fix + (q - self._q_fix) / self.capacity_ah
        elif cfg.capacity_soc_update == "line":
            # the line's SOC now, from all anchors
            with np.errstate(divide="ignore", invalid="ignore"):
                target = ss / n + slope * (q - sq / n)
        else:
            return
        move = good & np.isfinite(target) & (np.abs(target - self.soc) > cfg.reanchor_min_soc)
        if any_cell(move):
            # the OCV difference moves out of the model exactly like a c0 compensation
            target = np.clip(target, 0.0, 1.0)
            dv = np.where(move, self._ocv(target) - self._ocv(self.soc), 0.0)
            self.soc = np.where(move, target, self.soc)
            self.identifier.shift_bias(dv, move)
            self._shift_c0_window(dv)

    def _voltage_line(self, i: np.ndarray, v: np.ndarray, use: np.ndarray, every_use: bool) -> None:
        """The c0 method's voltage line (module docstring, "At a bound"): a point every ``VOLTAGE_LINE_EVERY_S``
        for the identified cells averaged ``VOLTAGE_LINE_TAU_S``, its capacity and the flag.

        The averages take the period's ``n`` used samples at once: their mean ``y_b`` with the gain of ``n``
        samples, ``y_m += (1 - (1 - a)^n) (y_b - y_m)`` (``a = 1 - exp(-Ts / tau)``; the first period after a
        start or rest: ``y_m = y_b``), two sums a sample instead of three averages."""
        if every_use:
            self._v_sum += v
            self._i_sum += i
            self._n_all += 1
        else:
            self._v_sum += np.where(use, v, 0.0)
            self._i_sum += np.where(use, i, 0.0)
            self._n_sum += use
        if self.samples % self._vline_every:
            return
        n = self._n_sum + self._n_all
        seen = n > 0
        nn = np.maximum(n, 1)
        g = np.where(seen, np.where(self._v_warm == 0, 1.0, -np.expm1(n * self._log_keep)), 0.0)  # 1 - (1 - a)^n
        self._v_mean += g * (self._v_sum / nn - self._v_mean)
        self._i_mean += g * (self._i_sum / nn - self._i_mean)
        self._q_mean += g * (self._charge_ref_ah - self._q_mean)
        self._v_warm += n
        self._v_sum[:], self._i_sum[:], self._n_sum[:], self._n_all = 0.0, 0.0, 0, 0
        sel = (self._v_warm >= self._vline_warm) & self.identifier.identified & np.isfinite(self.soc)
        if not any_cell(sel):
            return
        p = self.identifier.params
        s = self._soc_at(self._v_mean - (p.r0_ohm + p.r1_ohm + p.r2_ohm) * self._i_mean)
        sel &= np.isfinite(s)
        q = self._q_mean
        add = np.stack([np.ones_like(q), q, s, q * q, q * s, s * s], axis=1)
        self._vline += np.where(sel[:, None], add, 0.0)
        self._vq_min = np.where(sel, np.minimum(self._vq_min, q), self._vq_min)
        self._vq_max = np.where(sel, np.maximum(self._vq_max, q), self._vq_max)
        self.capacity_voltage_ah = self._voltage_capacity()
        self.capacity_at_bound = self._capacity_side_c0(*self._capacity_line()[1:])

    def _voltage_capacity(self) -> np.ndarray:
        """:func:`voltage_line_capacity_ah` of this estimator's voltage line."""
        return voltage_line_capacity_ah(self._vline, np.stack([self._vq_min, self._vq_max], axis=1))

    def _capacity_line(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The anchor line ``s = s_0 + q / Q`` by least squares over all anchors: ``(slope, Q = 1 / slope,
        fits)``; ``fits`` where ``Q`` is finite and positive and the RMS residual is below ``capacity_max_rmse``."""
        slope, q_est, resid_var = _line_fit(self._cap)
        with np.errstate(invalid="ignore"):
            fits = np.isfinite(q_est) & (q_est > 0) & (np.sqrt(resid_var) < self.config.capacity_max_rmse)
        return slope, q_est, fits

    def _bound_side(self, q_ah: np.ndarray) -> np.ndarray:
        """-1 where ``q_ah`` is at or below the low bound (within ``CAPACITY_BOUND_TOL``), +1 at or above the
        high one, 0 inside (int8 per cell)."""
        low = q_ah <= self._capacity_lo_ah * (1.0 + CAPACITY_BOUND_TOL)
        high = q_ah >= self._capacity_hi_ah * (1.0 - CAPACITY_BOUND_TOL)
        return high.astype(np.int8) - low.astype(np.int8)

    def _capacity_side_c0(self, q_est: np.ndarray, fits: np.ndarray) -> np.ndarray:
        """The c0 method's :attr:`capacity_at_bound`: the capacity in use outside the bounds, else the anchor
        line's capacity at a bound where the line fits and its anchors span ``capacity_min_span`` of it."""
        in_use = self._bound_side(self.capacity_ah)
        with np.errstate(invalid="ignore"):
            evidence = fits & (self._q_max - self._q_min >= self.config.capacity_min_span * q_est)
        line = np.where(evidence, self._bound_side(np.where(evidence, q_est, self.capacity_ah)), 0).astype(np.int8)
        with np.errstate(invalid="ignore"):  # the voltage line: stated more than 2x its capacity, or under half
            ratio = self.capacity_stated_ah / self.capacity_voltage_ah  # NaN (no flag) until it counts
        volt = ((ratio < 1.0 / VOLTAGE_LINE_RATIO_MAX).astype(np.int8)
                - (ratio > VOLTAGE_LINE_RATIO_MAX).astype(np.int8))
        line = np.where(line != 0, line, volt)
        return np.where(in_use != 0, in_use, line).astype(np.int8)

    # ------------------------------------------------------------------
    @property
    def params(self) -> dict[str, np.ndarray]:
        return self.identifier.params.as_dict()

    def state_dict(self) -> dict[str, np.ndarray]:
        s = {f"id.{k}": v for k, v in self.identifier.state_dict().items()}
        s.update(
            soc=self.soc.copy(),
            capacity_ah=self.capacity_ah.copy(),
            capacity_estimated=self.capacity_estimated.copy(),
            c0_buf=self._c0_buf.copy(),
            c0_head=np.array(self._c0_head),
            c0_count=self._c0_count.copy(),
            i_prev=self._i_prev.copy(),
            i_hold=np.stack([self._i_hold, self._i_dev2, self._n_lost.astype(float)], axis=1),
            charge_ah=self.charge_ah.copy(),
            charge_ref_ah=self._charge_ref_ah.copy(),
            temperature_c=self.temperature_c.copy(),
            soc_fix=self._soc_fix.copy(),
            q_fix=self._q_fix.copy(),
            corrections=self.corrections.copy(),
            cap=self._cap.copy(),
            q_min=self._q_min.copy(),
            q_max=self._q_max.copy(),
            vline=self._vline.copy(),
            vline_q_range=np.stack([self._vq_min, self._vq_max], axis=1),
            samples=np.array(self.samples),
            rest_due=self._rest_due.copy(),  # a rest's OCV reading still to be taken (rest())
            rest_n=self._rest_n.copy(),  # samples at rest in a row (update, "A park with the gateway awake")
            # the start temperature (update): the priors' temperature, readings taken, next due, the readings
            prior_temperature=np.column_stack([self._t_prior, self._t_start_n, self._t_start_next, self._t_start]),
        )
        if self._hyst is not None:
            s.update({f"hyst.{k}": v for k, v in self._hyst.state_dict().items()})
        if self.ekf is not None:
            s.update({f"ekf.{k}": v for k, v in self.ekf.state_dict().items()})
        return s

    def _check_state(self, s: dict[str, np.ndarray]) -> None:
        """A well-formed state whose values no cell can have (a poisoned or hand-edited file) is refused:
        resumed, a zero capacity reads every SOC as 0 and a negative one counts backwards, for good."""
        lo, hi = self.config.capacity_bounds
        q = np.asarray(s["capacity_ah"], dtype=float)
        ok = np.isfinite(q) & (q >= lo * self.capacity_stated_ah) & (q <= hi * self.capacity_stated_ah)
        if not all_cells(ok):
            raise ValueError(f"state field 'capacity_ah' holds {q[~ok][:3].tolist()} Ah, outside {lo:g}..{hi:g} "
                             f"times the stated capacity")
        soc = np.asarray(s["soc"], dtype=float)
        if np.any(np.isinf(soc) | (soc < 0.0) | (soc > 1.0)):  # NaN is a cell without a start SOC yet
            raise ValueError("state field 'soc' holds values outside [0, 1]")
        for key in ("charge_ah", "i_prev", "c0_buf"):
            if not np.all(np.isfinite(np.asarray(s[key], dtype=float))):
                raise ValueError(f"state field {key!r} holds non-finite values")

    def load_state_dict(self, s: dict[str, np.ndarray]) -> None:
        """Restore a saved state; raises ValueError (naming the field) when it does not fit."""
        n = self.n_cells
        for key in ("soc", "capacity_ah", "charge_ah", "i_prev"):
            if np.shape(s[key]) != (n,):
                raise ValueError(f"state field {key!r} has shape {np.shape(s[key])}, expected ({n},)")
        if np.shape(s["c0_buf"]) != self._c0_buf.shape:
            raise ValueError("state field 'c0_buf' does not match the c0 window of this configuration")
        self._check_state(s)
        self.identifier.load_state_dict({k[3:]: v for k, v in s.items() if k.startswith("id.")})
        self.soc = np.asarray(s["soc"], dtype=float).copy()
        self.capacity_ah = np.asarray(s["capacity_ah"], dtype=float).copy()
        self.capacity_estimated = np.asarray(s["capacity_estimated"], dtype=bool).copy()
        self._c0_buf = np.asarray(s["c0_buf"], dtype=float).copy()
        self._c0_head = int(s["c0_head"])
        self._c0_count = np.asarray(s["c0_count"], dtype=np.int64).copy()
        self._c0_sum = self._c0_buf.sum(axis=1)
        self._c0_sq = np.einsum("nw,nw->n", self._c0_buf, self._c0_buf)
        self._i_prev = np.asarray(s["i_prev"], dtype=float).copy()
        # states saved before a lost current was held: the running mean starts from the last current
        hold = np.asarray(s.get("i_hold", np.stack([self._i_prev, np.zeros(n), np.zeros(n)], axis=1)), dtype=float)
        if hold.shape != (n, 3) or not np.all(np.isfinite(hold)):
            raise ValueError(f"state field 'i_hold' has shape {hold.shape} or non-finite values, expected ({n}, 3)")
        self._i_hold, self._i_dev2 = hold[:, 0].copy(), np.maximum(hold[:, 1], 0.0)
        self._n_lost = np.maximum(hold[:, 2], 0.0).astype(np.int64)
        self.charge_ah = np.asarray(s["charge_ah"], dtype=float).copy()
        # states saved before temperature existed: the count was at the reference temperature
        self._charge_ref_ah = np.asarray(s.get("charge_ref_ah", self.charge_ah), dtype=float).copy()
        self.temperature_c = np.asarray(s.get("temperature_c", self.temperature_c), dtype=float).copy()
        if self._t_aware:
            self._rel_q = np.asarray(self.ocv.relative_capacity(self.temperature_c), dtype=float)
        self._take_slow_branch_floor()
        # states saved before the recount existed: count from where the cells are now
        self._soc_fix = np.asarray(s.get("soc_fix", self.soc), dtype=float).copy()
        self._q_fix = np.asarray(s.get("q_fix", self._charge_ref_ah), dtype=float).copy()
        self.corrections = np.asarray(s["corrections"], dtype=np.int64).copy()
        self._cap = np.asarray(s["cap"], dtype=float).copy()
        self._q_min = np.asarray(s["q_min"], dtype=float).copy()
        self._q_max = np.asarray(s["q_max"], dtype=float).copy()
        # states saved before the voltage line existed: it starts afresh (its averages always do)
        self._vline = np.asarray(s.get("vline", np.zeros((n, 6))), dtype=float).copy()
        q_range = np.asarray(s.get("vline_q_range", np.tile([np.inf, -np.inf], (n, 1))), dtype=float)
        if self._vline.shape != (n, 6) or q_range.shape != (n, 2):
            raise ValueError(f"state field 'vline' or 'vline_q_range' has the wrong shape for {n} cells")
        self._vq_min, self._vq_max = q_range[:, 0].copy(), q_range[:, 1].copy()
        self._v_warm = np.zeros(n, dtype=np.int64)
        self._v_sum, self._i_sum, self._n_sum, self._n_all = np.zeros(n), np.zeros(n), np.zeros(n, dtype=np.int64), 0
        self.capacity_voltage_ah = self._voltage_capacity()
        # derived, not saved: from the capacity (EKF) and the anchor line (c0) just restored
        self.capacity_at_bound = (self._bound_side(self.capacity_ah) if self.ekf is not None
                                  else self._capacity_side_c0(*self._capacity_line()[1:]))
        self.samples = int(s["samples"])
        # states saved before it existed: no reading due
        due = np.asarray(s.get("rest_due", np.zeros(n, dtype=bool)), dtype=bool)
        if due.shape != (n,):
            raise ValueError(f"state field 'rest_due' has shape {due.shape}, expected ({n},)")
        self._rest_due = due.copy()
        self._any_rest_due = any_cell(self._rest_due)
        rest_n = np.asarray(s.get("rest_n", np.zeros(n)), dtype=float)  # (saved before it existed: none yet)
        if rest_n.shape != (n,) or not np.all(np.isfinite(rest_n)):
            raise ValueError(f"state field 'rest_n' has shape {rest_n.shape} or non-finite values, expected ({n},)")
        self._rest_n = np.maximum(rest_n, 0.0).astype(np.int64)
        self._any_parked = any_cell(self._parked())
        # states saved before it existed: the priors stay where they were saved, at an unknown temperature
        k = PRIOR_TEMPERATURE_READINGS
        pt = np.asarray(s.get("prior_temperature", np.column_stack([np.full(n, np.nan), np.full((n, 2), k),
                                                                    np.full((n, k), np.nan)])), dtype=float)
        if pt.shape != (n, k + 3) or not np.all(np.isfinite(pt[:, 1:3])) or np.any((pt[:, 1] < 0) | (pt[:, 1] > k)):
            raise ValueError(f"state field 'prior_temperature' has shape {pt.shape} or invalid counts, "
                             f"expected ({n}, {k + 3})")
        self._t_prior = pt[:, 0].copy()
        self._t_start_n = pt[:, 1].astype(np.int64)
        self._t_start_next = pt[:, 2].astype(np.int64)
        self._t_start = pt[:, 3:].copy()
        self._t_start_open = any_cell(self._t_start_n < k)
        if self._hyst is not None:
            if "hyst.h" in s:
                self._hyst.load_state_dict({"h": s["hyst.h"], "s": s["hyst.s"]})
                self.hysteresis_state = self._hyst.h.copy()
            else:
                # a state saved without hysteresis (older version, or the option was off): every
                # other field is kept and the branch is guessed from the SOC, as at a start
                self._start_hysteresis(np.ones(n, dtype=bool))
        if self.ekf is not None and "ekf.p" in s:
            # a state saved by the c0 method keeps the EKF's fresh start (initial_soc_sigma)
            self.ekf.load_state_dict({k[4:]: v for k, v in s.items() if k.startswith("ekf.") and k != "ekf.shift_v"})
            # a state saved while EKF moves were still pending for the identifier (older versions
            # shifted in millivolt steps): shift them now
            pending = np.asarray(s.get("ekf.shift_v", np.zeros(n)), dtype=float)
            if pending.shape == (n,) and np.all(np.isfinite(pending)) and any_cell(pending):
                self.identifier.shift_bias(pending)


def _line_fit(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The least-squares line ``s = s_0 + q / Q`` of weighted sums (n, sq, ss, sqq, sqs, sss per cell):
    ``(slope, Q = 1 / slope, residual variance)``."""
    n, sq, ss, sqq, sqs, sss = np.asarray(sums, dtype=float).T
    with np.errstate(divide="ignore", invalid="ignore"):
        var_q = sqq / n - (sq / n) ** 2
        cov = sqs / n - (sq / n) * (ss / n)
        var_s = sss / n - (ss / n) ** 2
        slope = cov / var_q
        return slope, 1.0 / slope, np.maximum(var_s - slope * cov, 0.0)


def voltage_line_capacity_ah(vline, q_range) -> np.ndarray:
    """The c0 method's voltage-line capacity (module docstring, "At a bound") per cell from its sums and charge
    range (a state's ``vline``, ``vline_q_range``): where its points moved ``VOLTAGE_LINE_MIN_MOVE`` of SOC
    along it, else NaN (an EKF estimator's state: none)."""
    q_v = _line_fit(vline)[1]
    q_range = np.asarray(q_range, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        moved = (q_range[:, 1] - q_range[:, 0]) / q_v
        return np.where(np.isfinite(q_v) & (q_v > 0) & (moved >= VOLTAGE_LINE_MIN_MOVE), q_v, np.nan)
