#!/usr/bin/env python3
"""The SOC matrix over ../shared/data, and the README table (:mod:`bms_estimator.soc_matrix`).

    python scripts/soc_matrix.py [--readme] [--json OUT] [--methods c0,ekf] [--files GLOB] [--set KEY=VALUE]
                                 [--starts full,full-20,mid+10,mid-10,at50+20,at75-5,...] [--no-rest-over-gaps]
                                 [--current-gain G] [--current-offset-a B] [--ocv-jitter-mv J --seed S]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bms_estimator.core.soc import SOC_METHODS  # noqa: E402
from bms_estimator.data import shared_data_dir  # noqa: E402
from bms_estimator.soc_matrix import (  # noqa: E402
    CELLS,
    STARTS,
    check_start,
    markdown,
    run_cell,
    summary_lines,
    summary_table,
)


def _setting(value: str):
    """A ``--set`` value: true/false, a number, else the text (a method name, say)."""
    if value.lower() in ("true", "false"):
        return value.lower() == "true"
    try:
        return float(value)
    except ValueError:
        return value


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--methods", default=None, help="comma-separated SOC methods (default: every one the core has)")
    ap.add_argument("--files", default="*", help="glob over cell/ambient/file, e.g. 'lg-hg2/25degC/*'")
    ap.add_argument("--no-leave-out", action="store_true", help="skip the runs with the file's own table left out")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an estimator setting to try (SocConfig field, or ekf.FIELD / identifier.FIELD)")
    ap.add_argument("--starts", default=",".join(STARTS),
                    help="comma-separated starts (default: the README's four); atP+E / atP-E = at P %% of the file, "
                         "the reference + or - E %%; ocv = at the start, read from the first sample's voltage; "
                         "atPocv = at P %% of the file, read from the voltage there (a gateway started mid-drive)")
    ap.add_argument("--current-gain", type=float, default=1.0, metavar="G",
                    help="stress test: every file's current times G before the estimator and the reference see it "
                         "(a cell G times the capacity its OCV tables were measured on, or a current sensor's gain "
                         "error); default 1")
    ap.add_argument("--current-offset-a", type=float, default=0.0, metavar="B",
                    help="stress test: B amperes added to the current the estimator and plain counting read, not "
                         "to the reference's (a current sensor's zero offset; charge positive); default 0")
    ap.add_argument("--ocv-jitter-mv", type=float, default=0.0, metavar="J",
                    help="robustness: every knot of the estimator's OCV tables moved by a normal error of sigma J mV "
                         "(not the reference's), drawn with --seed; default 0")
    ap.add_argument("--seed", type=int, default=0, help="the draw of --ocv-jitter-mv (default 0)")
    ap.add_argument("--no-rest-over-gaps", dest="rest_over_gaps", action="store_false",
                    help="feed the files' logging gaps as load_recording fills them, instead of resting over them "
                         "as the service does at a time jump")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--readme", action="store_true",
                    help="write the summary into README.md between its markers and every run into docs/soc_matrix.md")
    args = ap.parse_args(argv)
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        overrides[key] = _setting(value)
    data = shared_data_dir()
    if data is None:
        print("no ../shared/data (or BMS_SHARED_DATA): the matrix needs the measured data", file=sys.stderr)
        return 2
    methods = args.methods.split(",") if args.methods else list(SOC_METHODS)
    try:
        starts = tuple(check_start(s.strip()) for s in args.starts.split(","))
    except ValueError as exc:
        print(f"--starts: {exc}", file=sys.stderr)
        return 2
    if not (args.current_gain > 0 and args.current_gain < float("inf")):
        print(f"--current-gain: a positive number, got {args.current_gain}", file=sys.stderr)
        return 2
    if not abs(args.current_offset_a) < float("inf"):
        print(f"--current-offset-a: a finite number, got {args.current_offset_a}", file=sys.stderr)
        return 2
    if not (0.0 <= args.ocv_jitter_mv < float("inf")):
        print(f"--ocv-jitter-mv: a number >= 0, got {args.ocv_jitter_mv}", file=sys.stderr)
        return 2
    if args.readme and (starts != STARTS or args.current_gain != 1.0 or args.current_offset_a != 0.0
                        or args.ocv_jitter_mv != 0.0):
        print("--readme writes the README's four starts at the files' own current and tables only; drop --starts / "
              "--current-gain / --current-offset-a / --ocv-jitter-mv or --readme", file=sys.stderr)
        return 2
    if args.readme and not args.rest_over_gaps:
        print("--readme writes the default run (the logging gaps rested over); drop --no-rest-over-gaps or --readme",
              file=sys.stderr)
        return 2
    rows = []
    present = sorted(d.name for d in data.iterdir() if d.is_dir())
    for name in present:
        if name not in CELLS:
            print(f"{data / name}: skipped, no stated capacity for a cell named {name!r} "
                  f"(known: {', '.join(CELLS)})", file=sys.stderr)
    for cell in CELLS:
        if cell not in present:
            print(f"{data / cell}: absent, {cell} not run", file=sys.stderr)
            continue
        rows += run_cell(data, cell, methods, args.files, not args.no_leave_out, overrides, starts,
                         args.rest_over_gaps, args.current_gain, args.current_offset_a, 1e-3 * args.ocv_jitter_mv,
                         args.seed)
    for line in summary_lines(rows):
        print(line)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    if args.readme:
        readme = ROOT / "README.md"
        text = readme.read_text()
        a, b = "<!-- soc-matrix:begin -->", "<!-- soc-matrix:end -->"
        body = "\n".join(["", summary_table(rows), "", *[f"* {s}" for s in summary_lines(rows)], ""])
        (ROOT / "docs" / "soc_matrix.md").write_text(
            "# The SOC matrix, every run\n\nMade by `python scripts/soc_matrix.py --readme` (see the README's SOC "
            "section for how it is scored).\n\n" + markdown(rows) + "\n")
        if a in text and b in text:
            text = text[: text.index(a) + len(a)] + body + text[text.index(b):]
            readme.write_text(text)
        else:
            print("README.md has no soc-matrix markers; table not written", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
