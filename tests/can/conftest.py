"""Fixtures for the CAN-side tests (DBCs); frame builders are in bmscan_helpers.py."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:  # the package may not be installed
    sys.path.insert(0, str(REPO_ROOT))

from bms_estimator.can.dbc import load_db, load_project_db  # noqa: E402


def foxbms_dbc_path() -> Path | None:
    env = os.environ.get("BMS_FOXBMS_DBC")
    candidates = [Path(env)] if env else []
    candidates += [
        REPO_ROOT.parent / "shared" / "dbc" / "foxbms" / "foxbms.dbc",
        Path("/work/shared/dbc/foxbms/foxbms.dbc"),
    ]
    return next((p for p in candidates if p.is_file()), None)


@pytest.fixture(scope="session")
def project_db():
    return load_project_db()


@pytest.fixture(scope="session")
def foxbms_db():
    path = foxbms_dbc_path()
    if path is None:
        pytest.skip("foxBMS DBC not found (../shared/dbc/foxbms/foxbms.dbc or $BMS_FOXBMS_DBC)")
    return load_db(path)
