"""Location and loading of the project's own CAN database.

The DBC lives at ``dbc/bms_estimator.dbc`` in the repository and is shipped as
package data through the symlink ``bms_estimator/dbc/bms_estimator.dbc``
(``-> ../../dbc/bms_estimator.dbc``; a wheel build copies the target).
The file itself documents frame layouts, identifiers and scalings in its
``CM_`` comments.
"""

from __future__ import annotations

import functools
from pathlib import Path

import cantools
from cantools.database.can import Database

__all__ = ["project_dbc_path", "load_project_db", "load_db"]

_DBC_NAME = "bms_estimator.dbc"


def project_dbc_path() -> Path:
    """Path of the project's DBC (package data first, then the repository copy).

    Raises ``FileNotFoundError`` naming both places if neither exists.
    """
    pkg_dir = Path(__file__).resolve().parent.parent  # bms_estimator/
    candidates = [
        pkg_dir / "dbc" / _DBC_NAME,  # package data (symlink in a checkout)
        pkg_dir.parent / "dbc" / _DBC_NAME,  # repository layout
    ]
    for path in candidates:
        if path.is_file():
            return path
    raise FileNotFoundError(f"{_DBC_NAME} not found; looked at: " + ", ".join(map(str, candidates)))


@functools.lru_cache(maxsize=1)
def load_project_db() -> Database:
    """The project's DBC, loaded once in strict mode (cached; treat it as read-only)."""
    return load_db(project_dbc_path())


def load_db(path: str | Path | None = None) -> Database:
    """Load a DBC in strict mode; ``None`` = the project's DBC."""
    if path is None:
        return load_project_db()
    db = cantools.database.load_file(str(path), strict=True)
    if not isinstance(db, Database):  # pragma: no cover - a .kcd/.arxml of a non-CAN bus
        raise TypeError(f"{path}: not a CAN database")
    return db
