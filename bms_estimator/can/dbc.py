"""Location and loading of the project's own CAN database.

The DBC lives at ``dbc/bms_estimator.dbc`` in the repository and is shipped as
package data through the symlink ``bms_estimator/dbc/bms_estimator.dbc``
(``-> ../../dbc/bms_estimator.dbc``; a wheel build copies the target).
The file itself documents frame layouts, identifiers and scalings in its
``CM_`` comments.

Its ranges are an 18650's (R0 to 65.5 mOhm in 8 uOhm steps, C1 to 13,107 F,
CapacityMean to 65.5 Ah). ``dbc/bms_estimator_large_cell.dbc`` (the name
``large-cell`` wherever a DBC is chosen, e.g. the service's ``can.dbc``) is the
same database, frame for frame and bit for bit, with the scalings of R0, R1, R2,
C1, C2 and CapacityMean made for cells of about 20-600 Ah: a 57 Ah cell's C1 of
30,000 F went out as 13,106.8 F, and its R1 of 0.33 mOhm in 8 uOhm steps.
"""

from __future__ import annotations

import functools
from pathlib import Path

import cantools
from cantools.database.can import Database

__all__ = ["PROJECT_DBCS", "LARGE_CELL_AH", "project_dbc_path", "load_project_db", "load_db"]

#: the shipped databases by name: the project's (an 18650's ranges) and its large-cell variant
PROJECT_DBCS = {"default": "bms_estimator.dbc", "large-cell": "bms_estimator_large_cell.dbc"}
#: from this cell capacity on the ``large-cell`` variant's ranges are the cell's (below it the project DBC's)
LARGE_CELL_AH = 20.0


def project_dbc_path(name: str = "default") -> Path:
    """Path of a shipped DBC by its name in :data:`PROJECT_DBCS` (package data first, then the repository copy).

    Raises ``FileNotFoundError`` naming both places if neither exists.
    """
    file_name = PROJECT_DBCS[name]
    pkg_dir = Path(__file__).resolve().parent.parent  # bms_estimator/
    candidates = [
        pkg_dir / "dbc" / file_name,  # package data (symlink in a checkout)
        pkg_dir.parent / "dbc" / file_name,  # repository layout
    ]
    for path in candidates:
        if path.is_file():
            return path
    raise FileNotFoundError(f"{file_name} not found; looked at: " + ", ".join(map(str, candidates)))


@functools.lru_cache(maxsize=len(PROJECT_DBCS))
def load_project_db(name: str = "default") -> Database:
    """A shipped DBC (:data:`PROJECT_DBCS`), loaded once in strict mode (cached; treat it as read-only)."""
    db = cantools.database.load_file(str(project_dbc_path(name)), strict=True)
    if not isinstance(db, Database):  # pragma: no cover
        raise TypeError(f"{name}: not a CAN database")
    return db


def load_db(path: str | Path | None = None) -> Database:
    """Load a DBC in strict mode; ``None`` = the project's DBC, a name of :data:`PROJECT_DBCS` (and no file of
    that name here) = that shipped DBC, else a file."""
    if path is None:
        return load_project_db()
    if str(path) in PROJECT_DBCS and not Path(path).exists():
        return load_project_db(str(path))
    db = cantools.database.load_file(str(path), strict=True)
    if not isinstance(db, Database):  # pragma: no cover - a .kcd/.arxml of a non-CAN bus
        raise TypeError(f"{path}: not a CAN database")
    return db


def dbc_size_note(capacity_ah: float, dbc: str | Path | None) -> str | None:
    """What to say when the shipped DBC chosen (``dbc``: None or a name of :data:`PROJECT_DBCS`; a file of the
    user's own is theirs) is not made for a cell of ``capacity_ah`` (None when it is)."""
    name = "default" if dbc is None else str(dbc)
    if name == "default" and capacity_ah >= LARGE_CELL_AH:
        return (f"can.dbc: the project DBC's ranges are an 18650's (C1 to 13,107 F, CapacityMean to 65.5 Ah, "
                f"R0/R1 in 8 uOhm steps); a {capacity_ah:g} Ah cell's values are clamped or coarse there: "
                'set can.dbc = "large-cell" (the same frames, scaled for cells of 20 Ah and up; every '
                "receiver of the output frames must then decode them with dbc/bms_estimator_large_cell.dbc: "
                "on the project DBC it reads R0, R1 and R2 four times, C1 and C2 a 25th and CapacityMean a "
                "tenth of the values sent)")
    if name == "large-cell" and capacity_ah < LARGE_CELL_AH / 2:
        return (f"can.dbc: the large-cell DBC's R0/R1 end at 16.38 mOhm, below a {capacity_ah:g} Ah cell's; "
                "leave can.dbc unset (the project DBC) for it, and every receiver of the output frames on "
                "dbc/bms_estimator.dbc")
    return None
