"""Small measured samples shipped with the package (see ATTRIBUTION.md, CC BY 4.0)."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

#: cell folder -> (nominal capacity in Ah, drive cycles shipped)
CELLS = {
    "panasonic-18650pf": (2.9, ("cycle_1", "cycle_2")),
    "lg-hg2": (3.0, ("udds", "la92")),
}


def sample_path(name: str) -> Path:
    """Path of a shipped sample file; a clear error lists what exists."""
    p = Path(str(files(__package__) / name))
    if not p.is_file():
        have = sorted(x.name for x in Path(str(files(__package__))).iterdir() if x.suffix in (".gz", ".csv"))
        raise FileNotFoundError(f"no shipped sample {name!r}; available: {', '.join(have)}")
    return p


def drive_cycle(cell: str, cycle: str) -> Path:
    return sample_path(f"{cell}_25degC_{cycle}_1s.csv.gz")


def ocv_table(cell: str) -> Path:
    return sample_path(f"{cell}_25degC_ocv.csv")
