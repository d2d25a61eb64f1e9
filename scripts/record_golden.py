"""Record the service's outputs on a small replayed log, for tests/golden/test_golden.py.

    python scripts/record_golden.py            # rewrites tests/golden/*.gz
    python scripts/record_golden.py --log-only # rewrites only the input log (a new input wire
                                               # format; the outputs must not change)

The input is ``bms-estimator encode-log`` of the shipped LG HG2 LA92 sample
(4 cells, 420 s, seed 3), stored as a candump log. The outputs are every CAN
frame the service sends and every MQTT payload it submits (topic, JSON text),
in order, with the CAN output and MQTT on and the default estimator settings.

Regenerate only on purpose: when the estimator's numbers change (a new core
default, say), not to make a failing restructuring pass.
"""

from __future__ import annotations

import argparse
import gzip
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

GOLDEN = ROOT / "tests" / "golden"
LOG = GOLDEN / "pack4.log.gz"
CAN_OUT = GOLDEN / "can_out.jsonl.gz"
MQTT_OUT = GOLDEN / "mqtt_out.jsonl.gz"
CELL, CYCLE, N_CELLS, DURATION_S, SEED = "lg-hg2", "la92", 4, 420, 3


def make_log() -> None:
    import tempfile

    from bms_estimator.replay.encode_log import encode_log
    from bms_estimator.samples import drive_cycle

    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "pack4.log"
        encode_log(drive_cycle(CELL, CYCLE), out, N_CELLS, seed=SEED, duration_s=DURATION_S)
        LOG.write_bytes(gzip.compress(out.read_bytes(), mtime=0))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--log-only", action="store_true", help="rewrite only the input log (its outputs must not change)")
    ap.add_argument("--new-log", action="store_true", help="rewrite the input log before recording the outputs")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(GOLDEN))
    from golden_run import run_golden

    GOLDEN.mkdir(parents=True, exist_ok=True)
    if args.log_only:
        make_log()
        print(f"{LOG} rewritten; the recorded outputs are unchanged")
        return
    if not LOG.exists() or args.new_log:
        make_log()
    frames, payloads = run_golden(LOG, N_CELLS)
    with gzip.open(CAN_OUT, "wt", compresslevel=9) as fh:
        for f in frames:
            fh.write(json.dumps(f) + "\n")
    with gzip.open(MQTT_OUT, "wt", compresslevel=9) as fh:
        for p in payloads:
            fh.write(json.dumps(p) + "\n")
    print(f"{len(frames)} CAN frames, {len(payloads)} MQTT payloads -> {GOLDEN}")


if __name__ == "__main__":
    main()
