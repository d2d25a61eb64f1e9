"""What does the 2-RC model get wrong?  Model-error diagnosis of a recording (offline).

* :mod:`.extensions` - the baseline 2-RC model and one composable extension per
  candidate cause, fitted by batch output-error least squares;
* :mod:`.decide` - baseline, candidates, out-of-sample scoring and the decision
  (:func:`diagnose`);
* :mod:`.generator` - seeded synthetic cells on real current profiles with hidden
  effects of a given size (:func:`generate`), what the tests check the decision on;
* :mod:`.report` - the report folder (markdown and PNG figures).

Quick use::

    from bms_estimator.diagnose import Series, diagnose
    d = diagnose(Series.from_recording(rec, ocv, capacity_ah=2.9))
    d.cause, d.to_json()
"""

from __future__ import annotations

import time

from .decide import Candidate, DiagnoseConfig, Diagnosis, diagnose
from .extensions import CAUSES, FEATURES, Fit, Model, Series, fit_model, predict
from .generator import EFFECTS, GeneratedCell, generate, load_profile, profile_names
from .report import PHYSICS, write_report

__all__ = [
    "CAUSES",
    "FEATURES",
    "Candidate",
    "DiagnoseConfig",
    "Diagnosis",
    "EFFECTS",
    "Fit",
    "GeneratedCell",
    "Model",
    "PHYSICS",
    "Series",
    "bench_diagnose_s",
    "diagnose",
    "diagnose_recording",
    "fit_model",
    "generate",
    "hysteresis_params",
    "load_profile",
    "predict",
    "profile_names",
    "write_report",
]


def diagnose_recording(rec, ocv, capacity_ah: float, *, initial_soc: float = 1.0, validate=None,
                       config: DiagnoseConfig = DiagnoseConfig()) -> Diagnosis:
    """:func:`diagnose` on :class:`~bms_estimator.data.CellRecording` objects."""
    data = Series.from_recording(rec, ocv, capacity_ah, initial_soc)
    val = Series.from_recording(validate, ocv, capacity_ah, initial_soc) if validate is not None else None
    return diagnose(data, validate=val, config=config)


def hysteresis_params(d: Diagnosis, *, significant_only: bool = True):
    """The fitted hysteresis of a diagnosis as :class:`~bms_estimator.core.hysteresis.HysteresisParams`.

    For the online option (:class:`~bms_estimator.core.hysteresis.HysteresisState`);
    ``None`` when the hysteresis candidate was not fitted or (``significant_only``)
    did not earn its parameters.  ``gamma`` refers to the capacity the diagnosis
    was run with.
    """
    from ..core.hysteresis import HysteresisParams

    c = d.candidate("hysteresis")
    if c is None or not c.params or (significant_only and not c.significant):
        return None
    p = c.params
    return HysteresisParams(m_v=p["m_v"], m0_v=p["m0_v"], gamma=p["gamma"], h0=p["h0"])


def bench_diagnose_s() -> float:
    """Wall time [s] of ``diagnose`` (defaults: LIF warm start, pair stage) on a 4.4 h drive cycle.

    The shipped LG HG2 UDDS sample (15966 s at 1 s, 25 degC), stated capacity 3.0 Ah,
    cross-validated.  For ``bms-estimator bench``; a figure, not a test.
    """
    from .. import samples
    from ..core.ocv import OcvCurve
    from ..data import load_recording

    rec = load_recording(samples.drive_cycle("lg-hg2", "udds"))
    ocv = OcvCurve.from_csv(samples.ocv_table("lg-hg2"))
    data = Series.from_recording(rec, ocv, 3.0)
    t0 = time.perf_counter()
    diagnose(data)
    return time.perf_counter() - t0
