"""``bms-estimator demo``: the main job on a fresh machine, on measured data shipped in the package.

Default: a shipped drive cycle (LG HG2 LA92, 1 s) becomes the CAN traffic of a 16-cell pack
(cell 0 the measured cell, the others simulated with a seeded spread), is fed at full speed
frame by frame through the real estimator service (in process, without a CAN bus object:
decoder, sampler, estimator, MQTT every 30 s of log time per topic), which publishes
to MQTT (the broker given by ``--broker``, else a Mosquitto it starts, else an embedded
pure-Python broker, else MQTT off); a live view of the pack runs meanwhile, and a summary
(SOC error per cell against the reference, voltage RMSE, identified parameters, R0 ranking
against the injected spread) and a figure close the run. See ``bms_estimator/demo/``.

``--paper``: the paper's comparison (CT LIF vs DT ARX: train on one drive cycle, validate on
another) and the SOC estimation from a 20 % initial error, for the shipped Panasonic 18650PF
and LG HG2 samples; prints the figures and writes the plots (the README's results).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from ..analysis import compare_methods, reference_capacity, reference_soc, run_soc, soc_errors
from ..data import load_recording
from ..errors import EXIT_RUNTIME
from ..ocv_table import read_ocv_table
from ..samples import CELLS, drive_cycle, ocv_table
from .common import positive_float, write_json
from .outputs import check_outputs, folder_output

ATTRIBUTION = ("Data: P. Kollmeyer et al., Mendeley Data, CC BY 4.0 "
               "(see bms_estimator/samples/ATTRIBUTION.md)")


def add_parser(sub) -> None:
    p = sub.add_parser(
        "demo", help="a shipped drive cycle as a pack's CAN traffic through the estimator service (MQTT, live view)",
        description="Encodes a measured drive cycle shipped in the package as the CAN traffic of a pack "
                    "(cell 0 measured, the others simulated with a seeded spread), feeds it frame by frame through the "
                    "estimator service in process, publishes to MQTT, shows the pack live and "
                    "ends with a summary and a figure. --paper runs the offline paper comparison instead.",
    )
    p.add_argument("--output", type=Path, default=Path("bms-estimator-demo"), help="folder for the figure and JSON")
    p.add_argument("--paper", action="store_true",
                   help="the offline paper comparison (CT vs DT, SOC from a 20 %% error) on the shipped samples")
    p.add_argument("--cell", choices=sorted(CELLS), action="append",
                   help="shipped cell (default lg-hg2; with --paper: only this cell, repeatable)")
    p.add_argument("--cycle", default=None,
                   help="shipped drive cycle of the cell (default: la92 for lg-hg2, cycle_2 for panasonic-18650pf)")
    p.add_argument("--cells", type=int, default=16, help="cells in the pack (default 16)")
    p.add_argument("--seed", type=int, default=0, help="seed of the cell-to-cell spread (default 0)")
    p.add_argument("--speed", default="max",
                   help="replay speed: 'max' (default, as fast as the service goes) or a factor on real time (50 = 50x)")
    p.add_argument("--duration-s", type=positive_float, default=None,
                   help="replay only the first S seconds of the cycle (default: all of it)")
    p.add_argument("--broker", default="auto",
                   help="MQTT broker: HOST:PORT, or 'auto' (default: Mosquitto started on a free loopback port if "
                        "installed, else the embedded pure-Python broker, else MQTT off), 'mosquitto', 'embedded', "
                        "'none'")
    p.add_argument("--plain", action="store_true", help="plain progress lines instead of the live view")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_outputs([], [folder_output("--output", args.output)])
    if args.paper:
        return run_paper(args)
    return run_pack(args)


def run_pack(args: argparse.Namespace) -> int:
    """The service on a replayed pack (the default)."""
    from ..demo.broker import open_broker
    from ..demo.pipeline import MQTT_PUBLISH_PERIOD_S, prepare_pack, run_pipeline
    from ..demo.summary import analyse, format_summary, plot_run
    from ..replay.replay import parse_speed

    t_start = time.perf_counter()
    cells = args.cell or ["lg-hg2"]
    if len(cells) > 1:
        raise ValueError("--cell: give one cell for the pack demo (several only with --paper)")
    cell = cells[0]
    if not 1 <= args.cells <= 2000:
        raise ValueError(f"--cells must be 1..2000, got {args.cells}")
    speed = parse_speed(args.speed)
    out_dir: Path = args.output
    out_dir.mkdir(exist_ok=True)  # (its parent checked: check_outputs)
    out = sys.stdout
    # the broker (a process of its own, or Mosquitto) starts while the pack is prepared
    with contextlib.ExitStack() as stack:
        pool = stack.enter_context(ThreadPoolExecutor(1, thread_name_prefix="bms-demo-prepare"))
        prepared = pool.submit(prepare_pack, cell, args.cycle, args.cells, seed=args.seed, duration_s=args.duration_s)
        broker = stack.enter_context(open_broker(args.broker))
        setup = prepared.result()
        ref = setup.truth["reference"]
        print(f"bms-estimator demo: {setup.cell} {setup.cycle} ({setup.duration_s:.0f} s, 1 s samples) as the CAN "
              f"traffic of a {setup.n_cells}-cell pack: {len(setup.frames):,} frames (current 10 ms, cell voltages "
              f"100 ms, temperatures 1 s; project DBC), seed {setup.seed}; cell model identified on the measured cell "
              f"(simulation RMSE {ref['model_rmse_mv']:.1f} mV) in {setup.prepare_s:.1f} s", file=out, flush=True)
        truth_file = out_dir / "pack.truth.json"
        write_json(setup.truth, truth_file)
        live = sys.stdout.isatty() and not args.plain
        print(f"MQTT: {broker.describe()}", file=out, flush=True)
        if not broker.enabled:
            print("MQTT is disabled for this run: the service runs without publishing and the view reads its "
                  "state directly", file=out, flush=True)
        else:
            print(f"  topics: bms/demo/cell/<i>/state, bms/demo/pack/state, bms/demo/availability "
                  f"(watch with: bms-estimator dashboard --broker {broker.host}:{broker.port})", file=out, flush=True)
        print("Service: frames in process -> decoder -> 1 s samples -> SOC + 2-RC estimator"
              + (f" -> MQTT (each topic every {MQTT_PUBLISH_PERIOD_S:g} s of log time, mqtt.publish_period_s, "
                 "and the final states; the summary reads every sample)" if broker.enabled else "") + " "
              f"(replay speed {'max' if math.isinf(speed) else f'{speed:g}x'}; CAN output "
              "and health server off)", file=out, flush=True)
        if live:
            from ..demo.live import LiveView

            title = f"bms-estimator demo: {setup.n_cells}-cell pack, {setup.cell} {setup.cycle}"
            view_cm = LiveView(max_rows=max(8, -(-setup.n_cells // 2)) if setup.n_cells <= 32 else 16, title=title)
        else:
            from ..demo.live import PlainView

            view_cm = PlainView(out)
        with view_cm as view:
            result = asyncio.run(run_pipeline(setup, broker=broker, speed=speed, on_tick=view))
    a = analyse(setup, result)
    fig = plot_run(setup, result, a, out_dir / "pack.png")
    a["truth_json"] = str(truth_file)
    a["figure"] = str(fig)
    a["mqtt_broker"] = broker.describe()
    a["wall_s"] = time.perf_counter() - t_start
    write_json(a, out_dir / "pack_summary.json")
    print(format_summary(a, fig), file=out)
    print(f"\npack_summary.json, pack.truth.json and the figure in {out_dir}/; demo finished in {a['wall_s']:.0f} s. "
          f"{ATTRIBUTION}", file=out, flush=True)
    if broker.enabled and not a["mqtt_published"]:  # the MQTT half of the demo failed: a runtime error (exit 1)
        print(f"bms-estimator demo: error: MQTT broker {broker.host}:{broker.port} never reached: nothing was "
              "published (the summary above is the service's own state)", file=sys.stderr)
        return EXIT_RUNTIME
    return 0


def run_paper(args: argparse.Namespace) -> int:
    """The paper's comparison on the shipped samples (``--paper``; the README's results)."""
    from ..plots import plot_errors, plot_parameters, plot_soc

    out_dir: Path = args.output
    out_dir.mkdir(exist_ok=True)  # (its parent checked: check_outputs)
    summary = {}
    t_start = time.perf_counter()
    for cell in args.cell or sorted(CELLS):
        q_stated, (train_name, val_name) = CELLS[cell]
        ocv = read_ocv_table(ocv_table(cell))
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
    print(f"\nplots and summary.json in {out_dir}/ ({time.perf_counter() - t_start:.0f} s). {ATTRIBUTION}")
    return 0
