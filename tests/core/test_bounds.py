"""Every config with annotated bounds (the core's, diagnose's) refuses a value outside them, naming the field."""

import dataclasses
import typing

import pytest

from bms_estimator.core.identifier import IdentifierConfig
from bms_estimator.core.soc import SocConfig
from bms_estimator.core.soc_ekf import SocEkfConfig
from bms_estimator.core.soe import SoeConfig
from bms_estimator.core.soh import SohConfig
from bms_estimator.core.sop import SopConfig
from bms_estimator.core.sop_residual import ResidualConfig
from bms_estimator.core.sox import SoxConfig
from bms_estimator.diagnose.decide import DiagnoseConfig

CONFIGS = (IdentifierConfig, SocConfig, SocEkfConfig, SoeConfig, SohConfig, SopConfig, ResidualConfig, SoxConfig,
           DiagnoseConfig)


def _bounded(cls):
    """``(name, bound object)`` of every scalar field with an annotated bound."""
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        for meta in getattr(hints[f.name], "__metadata__", ()):
            yield f.name, meta


def _outside(meta):
    """A value just past the bound ``meta`` states."""
    for attr, step in (("gt", 0.0), ("ge", -1.0), ("lt", 0.0), ("le", 1.0)):
        bound = getattr(meta, attr, None)
        if bound is not None:
            return bound + step
    raise AssertionError(meta)


@pytest.mark.parametrize("cls", CONFIGS, ids=lambda c: c.__name__)
def test_a_value_past_any_annotated_bound_is_refused_by_name(cls):
    cls()  # the defaults are within their bounds
    cases = list(_bounded(cls))
    assert cases, f"{cls.__name__} states no bounds"
    for name, meta in cases:
        with pytest.raises(ValueError, match=name):
            cls(**{name: _outside(meta)})
        with pytest.raises(ValueError, match=name):
            cls(**{name: float("nan")})


def test_tuples_of_bounded_numbers_are_checked_element_by_element():
    with pytest.raises(ValueError, match="capacity_bounds"):
        SocConfig(capacity_bounds=(0.6, float("inf")))
    with pytest.raises(ValueError, match="discharge_derate"):
        SopConfig(discharge_derate=(0.3, 0.6, -0.1, 1.0, 0.0))
    with pytest.raises(ValueError, match="block_s_bounds"):
        DiagnoseConfig(block_s_bounds=(300.0, -1.0))


def test_a_value_that_is_not_a_number_is_refused_by_name():
    """A string or None where a bounded number belongs is refused like one out of bounds (no comparison is made)."""
    with pytest.raises(ValueError, match="voltage_sigma_v"):
        SocEkfConfig(voltage_sigma_v="0.015")
    with pytest.raises(ValueError, match="capacity_bounds"):
        SocConfig(capacity_bounds=(0.6, None))
