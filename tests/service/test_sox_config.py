"""[estimator.sop] (issue 14): the core's SopConfig, its bounds and cross-field rules named."""

import pytest

from bms_estimator.errors import ConfigError
from bms_estimator.service.config import EstimatorConfig, ServiceConfig


def test_sop_section_builds_the_core_config():
    cfg = EstimatorConfig(sop={"v_min": 2.8, "i_discharge_max_a": 15.0, "horizons_s": [5.0, 60.0]})
    sop = cfg.sox_config.sop
    assert sop.v_min == 2.8 and sop.i_discharge_max_a == 15.0 and sop.horizons_s == (5.0, 60.0)
    assert EstimatorConfig().sox_config.sop.horizons_s == (2.0, 10.0, 30.0)


@pytest.mark.parametrize("sop, words", [
    ({"v_min": 4.3}, "v_min"),
    ({"i_charge_max_a": -1.0}, "i_charge_max_a"),
    ({"charge_derate": [1.0]}, "charge_derate"),
    ({"v_mn": 2.5}, "v_mn"),
])
def test_bad_sop_settings_are_named(sop, words):
    from bms_estimator.service.config import _problems  # the service's own error lines

    with pytest.raises(Exception) as exc:
        ServiceConfig(estimator={"sop": sop})
    lines = _problems(exc.value) if not isinstance(exc.value, ConfigError) else exc.value.problems
    assert any(words in line and "estimator.sop" in line for line in lines), lines
