"""Fixtures for the CAN-side tests (DBCs); frame builders are in bmscan_helpers.py."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:  # the package may not be installed
    sys.path.insert(0, str(REPO_ROOT))

from bms_estimator.can.dbc import load_db, load_project_db  # noqa: E402
from tests.conftest import foxbms_dbc_path  # noqa: E402


@pytest.fixture(scope="session")
def project_db():
    return load_project_db()


@pytest.fixture(scope="session")
def foxbms_db():
    path = foxbms_dbc_path()
    if path is None:
        pytest.skip("foxBMS DBC not found (../shared/dbc/foxbms/foxbms.dbc or $BMS_FOXBMS_DBC)")
    return load_db(path)
