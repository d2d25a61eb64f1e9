#!/usr/bin/env python3
"""Rebuild the small measured samples shipped in bms_estimator/samples/ from ../shared/data.

Each drive cycle is averaged to 1 s (the estimator's sample period) and saved in the
same CSV layout; the OCV tables come from the cells' 25 degC C/20 tests (as
`bms-estimator ocv` builds them: with the test's median cell temperature and C/20 capacity).
Data: P. Kollmeyer et al. (CC BY 4.0), see bms_estimator/samples/ATTRIBUTION.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bms_estimator.core.ocv import OcvCurve
from bms_estimator.data import load_recording, save_recording, shared_data_dir
from bms_estimator.ocv_table import write_ocv_table

SAMPLES = Path(__file__).resolve().parents[1] / "bms_estimator" / "samples"
CYCLES = {
    "panasonic-18650pf": ["cycle_1", "cycle_2"],
    "lg-hg2": ["udds", "la92"],
}


def main(argv: list[str] | None = None) -> int:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args(argv)  # --help, and no stray options
    data = shared_data_dir()
    if data is None:
        print("../shared/data not found (set BMS_SHARED_DATA)", file=sys.stderr)
        return 2
    SAMPLES.mkdir(exist_ok=True)
    for cell, cycles in CYCLES.items():
        c20 = load_recording(data / cell / "25degC" / "c20_ocv.csv.gz", resample_s=None)
        curve = OcvCurve.from_c20(c20.time_s, c20.current_a, c20.voltage_v, temperature_c=c20.temperature_c)
        write_ocv_table(curve, SAMPLES / f"{cell}_25degC_ocv.csv")
        for cycle in cycles:
            rec = load_recording(data / cell / "25degC" / f"{cycle}.csv.gz", resample_s=1.0)
            out = save_recording(rec, SAMPLES / f"{cell}_25degC_{cycle}_1s.csv.gz")
            print(f"{out.name}: {len(rec)} samples, {out.stat().st_size / 1024:.0f} KiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
