"""``bms-estimator demo``: the main job on a fresh machine, on measured data shipped in the package.

Runs the paper's comparison (CT LIF vs DT ARX: train on one drive cycle, validate on
another) and the SOC estimation from a 20 % initial error, for the shipped Panasonic
18650PF and LG HG2 samples, prints the figures and writes the plots.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..analysis import compare_methods, reference_capacity, reference_soc, run_soc, soc_errors
from ..core.ocv import OcvCurve
from ..data import load_recording
from ..samples import CELLS, drive_cycle, ocv_table
from .common import write_json


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="run the estimator on the measured samples shipped in the package")
    p.add_argument("--output", type=Path, default=Path("bms-estimator-demo"), help="folder for plots and JSON")
    p.add_argument("--cell", choices=sorted(CELLS), action="append", help="only this cell (repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..plots import plot_errors, plot_parameters, plot_soc

    out_dir: Path = args.output
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = {}
    t_start = time.perf_counter()
    for cell in args.cell or sorted(CELLS):
        q_stated, (train_name, val_name) = CELLS[cell]
        ocv = OcvCurve.from_csv(ocv_table(cell))
        tr = load_recording(drive_cycle(cell, train_name))
        va = load_recording(drive_cycle(cell, val_name))
        res = compare_methods((tr.current_a, tr.voltage_v), (va.current_a, va.voltage_v), ocv, q_stated,
                              names=(train_name, val_name))
        m = res.metrics
        folder = out_dir / cell
        plot_parameters(tr.time_s, res.train.params, folder / "parameters_train.png", f"{cell} {train_name}: online parameters")
        plot_errors(va.time_s, va.voltage_v, res.validate.simulated_v, folder / "simulation_validate.png",
                    f"{cell} {val_name}: simulation with parameters from {train_name}", "simulation error [mV]")
        q_ref, src = reference_capacity(va.current_a, va.voltage_v, va.dt_s, ocv, q_stated)
        soc_ref = reference_soc(va.current_a, va.dt_s, q_ref)
        srun = run_soc(va.current_a, va.voltage_v, ocv, q_stated, 0.8)
        soc_fig = plot_soc(va.time_s, srun.soc, soc_ref, srun.capacity_ah, folder / "soc_validate.png",
                           f"{cell} {val_name}: SOC from a 20 % initial error")
        s = soc_errors(srun.soc, soc_ref, va.time_s)
        summary[cell] = {"compare": m, "soc": {**s, "capacity_ah_estimated": float(srun.capacity_ah[-1]),
                                                "capacity_ah_reference": q_ref, "reference_capacity_source": src}}
        print(f"\n{cell} (stated {q_stated} Ah, effective {res.capacity_ah:.3f} Ah): train {train_name}, validate {val_name}")
        print("  simulation RMSE, 20-90 % SOC [mV]      CT (LIF)   DT (ARX)   paper CT / DT")
        print(f"    training                           {m['train']['lif']['sim_rmse_mv']:8.1f}   {m['train']['arx']['sim_rmse_mv']:8.1f}   21.6 / 36.3")
        print(f"    validation                         {m['validate']['lif']['sim_rmse_mv']:8.1f}   {m['validate']['arx']['sim_rmse_mv']:8.1f}   17.3 / 53.8")
        print(f"  SOC from 20 % error: RMSE {s['soc_rmse_pct']:.2f} %, after 1 h {s['soc_rmse_pct_after_3600s']:.2f} % "
              f"(paper 2.3 %); figure {soc_fig}")
    write_json(summary, out_dir / "summary.json")
    print(f"\nplots and summary.json in {out_dir}/ ({time.perf_counter() - t_start:.0f} s). "
          "Data: P. Kollmeyer et al., Mendeley Data, CC BY 4.0 (see bms_estimator/samples/ATTRIBUTION.md)")
    return 0
