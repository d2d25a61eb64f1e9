"""The foxBMS DBC for the fleet tests (the same lookup as tests/can/conftest.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from bms_estimator.can.dbc import load_db

_spec = importlib.util.spec_from_file_location("_can_conftest", Path(__file__).parents[1] / "can" / "conftest.py")
_can_conftest = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_can_conftest)


@pytest.fixture(scope="session")
def foxbms_db():
    path = _can_conftest.foxbms_dbc_path()
    if path is None:
        pytest.skip("foxBMS DBC not found (../shared/dbc/foxbms/foxbms.dbc or $BMS_FOXBMS_DBC)")
    return load_db(path)
