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
    "diagnose",
    "fit_model",
    "generate",
    "load_profile",
    "predict",
    "profile_names",
    "write_report",
]
