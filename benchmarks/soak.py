"""Long-run soak of the service's data path: a measured drive cycle looped for many hours of log time.

``PYTHONPATH=. python -m benchmarks.soak --cells 192 --hours 26`` runs the real
:class:`~bms_estimator.service.daemon.Service` (MQTT on, pointed at a port nothing listens on, i.e. a
broker down for the whole run; state saves on; CAN output to a python-can ``virtual`` bus) and feeds it
in process (:meth:`Service.feed`, as the demo does) the frames of the demo's pack, the drive cycle
repeated back to back on epoch timestamps. Per hour of log time it prints the process RSS, the
Python heap (``tracemalloc`` with ``--tracemalloc``), the mean and the 99th percentile tick time
over that hour, the MQTT buffer, and the sizes of the containers that could grow.

Frames are thinned to the rates a big pack's gateway sees on one bus (current every 100 ms, each
cell voltage every 1 s, each temperature every 1 s) and re-stamped with the alive counters and CRC
across loops, so no frame fails the end-to-end checks at a loop boundary. ``--park-h`` puts a park
(no frames: a time jump, rested over) between two drives; with the LG la92 cycle (2.80 h) and
``--park-h 2.198888888888889`` every drive starts 5 h after the one before, so hours 1, 6, 11, ... are the
same part of the drive. ``calls_per_tick`` (Python and C calls of 30 profiled ticks after each
report) is a tick's cost that does not move with the machine's load.

Measured (192 cells, 31 h of log time, 6 drives and 6 parks, CAN output on, MQTT broker down all
along, publish_period_s 5, 2 shared cores at load 3-4): RSS 572 MiB at hour 1 (the demo's frame
arrays, ~560 MiB of it), 585 at hour 6, 591 at hour 31; Python objects 246,159 -> 246,221 (the
harness's own rows); calls per tick 10,142 / 10,106 / 10,099 at hours 1 / 6 / 31; tick 10-17 ms
mean, 26-68 ms p99 with the machine's load and no trend; MQTT buffer 193 (n_cells + 1) all along;
asyncio tasks 6; state file 700,516 bytes, 1073 saves; no CAN frame dropped, no tick error. With
``--tracemalloc`` (11 h): the Python heap 47.36 / 47.45 / 47.46 MiB at hours 1 / 6 / 11 (the harness's
per-hour frame lists included; 18.24 -> 18.31 MiB between the parks at hours 4 and 9).
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import resource
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cells", type=int, default=192)
    ap.add_argument("--hours", type=float, default=26.0)
    ap.add_argument("--cycle", default="la92")
    ap.add_argument("--t0", type=float, default=1.78e9, help="epoch of the first frame")
    ap.add_argument("--tracemalloc", action="store_true")
    ap.add_argument("--publish-period-s", type=float, default=0.0)
    ap.add_argument("--park-h", type=float, default=2.0, help="a park (no frames) between two drives")
    ap.add_argument("--can-output", action="store_true", help="send the CAN output frames (a virtual bus)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    return asyncio.run(run(args))


async def run(args: argparse.Namespace) -> int:
    from bms_estimator.can.dbc import load_project_db
    from bms_estimator.can.e2e import E2EStamper
    from bms_estimator.demo.pipeline import Frame, prepare_pack, service_config
    from bms_estimator.replay.encode_log import frame_arrays
    from bms_estimator.service.daemon import Service

    setup = prepare_pack("lg-hg2", args.cycle, args.cells, seed=0)
    fa = frame_arrays(setup.trace, current_period_s=0.1, voltage_period_s=1.0, temperature_period_s=1.0)
    db = load_project_db()
    stamper = E2EStamper(db, "default")
    drive_us = int(round(setup.trace.duration_s * 1e6))
    loop_us = drive_us + int(round(args.park_h * 3.6e9))  # a drive, then a park
    ids = fa.arbitration_id
    id_list = sorted(set(ids.tolist()))
    print(f"pack {args.cells} cells, cycle {args.cycle} {drive_us / 3.6e9:.2f} h + {args.park_h:g} h parked, {len(fa)} frames a loop "
          f"({len(fa) / (drive_us / 1e6):.0f}/s)", flush=True)

    class Broker:  # nothing listens there: the broker is down for the whole run
        enabled, host = True, "127.0.0.1"
        port = 9  # discard: refused on loopback

    with tempfile.TemporaryDirectory(prefix="bms-soak-") as tmp:
        cfg = service_config(setup, f"bms-soak-{os.getpid()}", Path(tmp) / "state.npz", Broker())
        cfg.mqtt.publish_period_s = args.publish_period_s
        cfg.state.save_interval_s = 60.0
        cfg.can.output.enabled = args.can_output
        from bms_estimator.service.logging import configure_logging

        configure_logging(level="INFO", fmt="json")
        svc = Service(cfg)
        ticks: list[float] = []
        svc.pipeline.observe_tick = lambda dt, obs=svc.metrics.observe_tick: (obs(dt), ticks.append(dt))
        # the calls a tick makes (Python and C functions, profiled on 30 ticks after each report): a cost
        # that does not depend on the machine's load, to tell a tick that grows from a busy machine
        prof = {"left": 30, "calls": 0, "ticks": 0}
        orig_tick = svc.pipeline.tick

        def counting_tick(sample, orig=orig_tick):
            if prof["left"] <= 0:
                return orig(sample)
            prof["left"] -= 1
            n = [0]

            def count(frame, event, arg):
                if event in ("call", "c_call"):
                    n[0] += 1
            sys.setprofile(count)
            try:
                return orig(sample)
            finally:
                sys.setprofile(None)
                prof["calls"] += n[0]
                prof["ticks"] += 1

        svc.pipeline.tick = counting_tick
        stop = asyncio.Event()
        task = asyncio.create_task(svc.run(stop))
        await asyncio.wait_for(svc.ready.wait(), 15)
        if args.tracemalloc:
            tracemalloc.start(1)
        t0_us = int(round(args.t0 * 1e6))
        hours_total = args.hours
        next_report_h = 1.0
        rows = []
        loop_k = 0
        base_snapshot = None
        wall0 = time.perf_counter()
        done = False
        while not done:
            data = fa.data.copy()
            for fid in id_list:
                m = ids == fid
                data[m] = stamper.stamp_rows(fid, fa.data[m])
            ts_us = t0_us + loop_k * loop_us + fa.t_us
            # slices of one hour of log time at most, so that the report falls on the hour
            a = 0
            n = len(fa)
            while a < n:
                h_now = (ts_us[a] - t0_us) / 3.6e9
                if h_now >= hours_total:
                    done = True
                    break
                lim_us = t0_us + int(round(next_report_h * 3.6e9))
                b = min(n, max(a + 1, int(np.searchsorted(ts_us, lim_us, side="left"))))
                ts = (ts_us[a:b] / 1e6).tolist()
                fids = ids[a:b].tolist()
                blob = data[a:b].astype("<u8").tobytes()
                ext = fa.extended
                await svc.feed(Frame(t, i, ext.get(i, True), blob[8 * k: 8 * k + 8])
                               for k, (t, i) in enumerate(zip(ts, fids)))
                a = b
                if b < n:  # the hour is over
                    await asyncio.sleep(0.05)  # the save task, the publisher
                    gc.collect()
                    tk = np.asarray(ticks)
                    ticks.clear()
                    pub = svc.publisher
                    row = {
                        "hour": round(next_report_h, 3),
                        "wall_s": round(time.perf_counter() - wall0, 1),
                        "rss_mib": round(rss_mib(), 1),
                        "maxrss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                        "tick_mean_ms": round(1e3 * float(tk.mean()), 3) if tk.size else None,
                        "tick_p99_ms": round(1e3 * float(np.percentile(tk, 99)), 3) if tk.size else None,
                        "ticks": int(tk.size),
                        "samples": svc.pipeline.counters.samples,
                        "mqtt_buffered": pub.buffered,
                        "mqtt_submitted_dict": len(pub._submitted),
                        "mqtt_dropped": pub.counters.dropped,
                        "tasks": len(asyncio.all_tasks()),
                        "gc_objects": len(gc.get_objects()),
                        "tick_errors": svc.pipeline.counters.tick_errors,
                        "decode_problems": {k: v for k, v in svc.decoder.counters.as_dict().items() if v and k not in ("frames", "decoded")},
                        "saves": svc.metrics.state_saves._value.get(),
                        "state_bytes": (Path(tmp) / "state.npz").stat().st_size if (Path(tmp) / "state.npz").exists() else None,
                        "rests": svc.pipeline.counters.rests,
                        "time_jumps": svc.sampler.counters.time_jumps,
                        "can_tx": svc.bus.counters.tx_frames if svc.bus is not None else None,
                        "can_tx_dropped": svc.bus.counters.tx_dropped if svc.bus is not None else None,
                        "soc_mean": round(float(np.nanmean(svc.estimator.soc)), 4),
                        "calls_per_tick": round(prof["calls"] / prof["ticks"], 1) if prof["ticks"] else None,
                    }
                    if args.tracemalloc:
                        cur, peak = tracemalloc.get_traced_memory()
                        row["py_heap_mib"] = round(cur / 2**20, 2)
                        snap = tracemalloc.take_snapshot()
                        if base_snapshot is None:
                            base_snapshot = snap
                        else:
                            top = snap.compare_to(base_snapshot, "lineno")[:5]
                            row["top_growth"] = [f"{s.traceback[0].filename.split('site-packages/')[-1]}:{s.traceback[0].lineno} {s.size_diff / 1024:+.0f} KiB {s.count_diff:+d}" for s in top]
                    prof.update(left=30, calls=0, ticks=0)
                    rows.append(row)
                    print(json.dumps(row), flush=True)
                    next_report_h += 1.0
            loop_k += 1
        stop.set()
        await asyncio.wait_for(task, 60)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
