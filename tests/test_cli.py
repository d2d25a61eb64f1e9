"""The command line on the shipped measured samples and on bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bms_estimator.cli.__main__ import main
from bms_estimator.core.ocv import OcvCurve
from bms_estimator.data import CellRecording, save_recording
from bms_estimator.ocv_table import read_ocv_table, write_ocv_table
from bms_estimator.samples import drive_cycle, ocv_table

PAN_OCV = str(ocv_table("panasonic-18650pf"))


def _c20_file(path, ocv: OcvCurve, q=3.0, hyst=0.02, temperature_c=None):
    """A synthetic C/20 test: discharge from full, 2 h rest, charge back, 60 s logging."""
    i_c20 = q / 20
    n = 20 * 60  # 20 h at 60 s per sample
    current = np.concatenate([np.full(n, -i_c20), np.zeros(120), np.full(n, i_c20)])
    soc = np.clip(1.0 + np.concatenate([[0], np.cumsum(current[:-1])]) * 60 / 3600 / q, 0, 1)
    v = ocv.ocv(soc) + 0.03 * current + hyst * np.sign(current)
    t = np.arange(len(current)) * 60.0
    temp = None if temperature_c is None else temperature_c + 0.5 * np.sin(t / 3600)
    save_recording(CellRecording(t, current, v, temp, "synthetic"), path)


def test_ocv_command_writes_a_table_the_others_read(tmp_path, nmc_like_ocv, capsys):
    src, out = tmp_path / "c20.csv", tmp_path / "ocv.csv"
    _c20_file(src, nmc_like_ocv)
    assert main(["ocv", str(src), "-o", str(out)]) == 0
    curve = read_ocv_table(out)
    s = np.linspace(0.1, 0.9, 9)
    np.testing.assert_allclose(curve.ocv(s), nmc_like_ocv.ocv(s), atol=0.01)
    assert np.all(curve.hysteresis(s) > 0.015)
    assert "C/20 branch capacities" in capsys.readouterr().out


def test_ocv_command_writes_the_tests_temperature_or_the_one_given(tmp_path, nmc_like_ocv, capsys):
    src, out = tmp_path / "c20.csv", tmp_path / "ocv.csv"
    _c20_file(src, nmc_like_ocv, temperature_c=10.0)
    assert main(["ocv", str(src), "-o", str(out)]) == 0
    header = out.read_text().splitlines()[0]
    assert header == "soc,ocv_v,hysteresis_v,temperature_c,capacity_ah"
    curve = read_ocv_table(out)
    assert curve.temperature_c == pytest.approx(10.0, abs=0.1)  # the median of the logged cell temperature
    assert curve.capacity_discharge_ah == pytest.approx(3.0, abs=0.01)
    assert "at 10" in capsys.readouterr().out
    assert main(["ocv", str(src), "-o", str(out), "--temperature-c", "-20"]) == 0
    assert read_ocv_table(out).temperature_c == -20.0
    bare = tmp_path / "bare.csv"
    _c20_file(bare, nmc_like_ocv)  # no temperature logged
    assert main(["ocv", str(bare), "-o", str(tmp_path / "bare_ocv.csv")]) == 0
    assert "give --temperature-c" in capsys.readouterr().out
    assert read_ocv_table(tmp_path / "bare_ocv.csv").temperature_c is None


def test_fit_takes_several_ocv_tables(tmp_path, capsys):
    lg = read_ocv_table(ocv_table("lg-hg2"))
    cold = write_ocv_table(OcvCurve(lg.soc, lg.ocv_v - 0.02 * (1 - lg.soc), lg.hysteresis_v, temperature_c=0.0,
                    capacity_discharge_ah=2.6), tmp_path / "cold.csv")
    data = str(drive_cycle("lg-hg2", "la92"))
    out = tmp_path / "fit.json"
    assert main(["fit", data, "--ocv", str(ocv_table("lg-hg2")), "--ocv", str(cold), "--capacity-ah", "3.0",
                 "--method", "arx", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["sim_rmse_mv"] > 0
    no_temperature = write_ocv_table(OcvCurve(lg.soc, lg.ocv_v), tmp_path / "bare.csv")
    assert main(["fit", data, "--ocv", str(ocv_table("lg-hg2")), "--ocv", str(no_temperature),
                 "--capacity-ah", "3.0", "--method", "arx"]) != 0
    err = capsys.readouterr().err
    assert "bare.csv: has no temperature_c column; give --temperature-c" in err and "Traceback" not in err


def test_compare_json_has_the_papers_figures(tmp_path):
    out = tmp_path / "cmp.json"
    rc = main(["compare", "--train", str(drive_cycle("panasonic-18650pf", "cycle_1")),
               "--validate", str(drive_cycle("panasonic-18650pf", "cycle_2")),
               "--ocv", PAN_OCV, "--capacity-ah", "2.9", "--json", str(out), "--plots", str(tmp_path / "plots")])
    assert rc == 0
    m = json.loads(out.read_text())
    for part in ("train", "validate"):
        for method in ("lif", "arx"):
            assert set(m[part][method]) >= {"sim_rmse_mv", "osa_rmse_mv"}
            assert 0 < m[part][method]["osa_rmse_mv"] < m["full_range"][part][method]["sim_rmse_mv"] + 50
    # the bound on the paper's chemistry; measured 9.2 mV when written
    assert m["validate"]["lif"]["sim_rmse_mv"] <= 25.0
    assert 2.6 < m["capacity_ah_estimated"] < 3.0  # 2.9 stated, the cell has less
    pngs = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert pngs == ["osa_train.png", "osa_validate.png", "parameters_train.png",
                    "simulation_train.png", "simulation_validate.png"]


def test_soc_and_fit_json(tmp_path):
    data = str(drive_cycle("lg-hg2", "la92"))
    lg_ocv = str(ocv_table("lg-hg2"))
    out = tmp_path / "soc.json"
    assert main(["soc", data, "--ocv", lg_ocv, "--capacity-ah", "3.0", "--initial-soc-error", "0.2",
                 "--json", str(out), "--plot", str(tmp_path / "soc.png")]) == 0
    s = json.loads(out.read_text())
    assert set(s) >= {"rmse_all_pct", "rmse_30min_pct", "rmse_1h_pct", "max_abs_pct", "capacity_ah_estimated",
                      "counting_stated_capacity", "soc_sigma_end"}
    assert s["reference_scored"] and "relaxed end rest" in s["reference"]  # LG files end with 600 s rest
    assert 2.78 < s["capacity_ah_reference"] < 2.86  # read on the C/20 discharge branch, not fitted
    # started 20 % low, corrected within the first half hour (measured 1.1 % from 30 min, 1.2 % after 1 h)
    assert s["rmse_30min_pct"] < 2.0 and s["rmse_1h_pct"] < 2.0 and s["rmse_all_pct"] < 20
    assert s["rmse_30min_pct"] < s["counting_stated_capacity"]["rmse_30min_pct"]  # 20 % low and never corrected
    assert 0 < s["soc_sigma_end"] < 0.1
    assert (tmp_path / "soc.png").stat().st_size > 10_000
    mean_curve = tmp_path / "soc_mean_curve.json"
    assert main(["soc", data, "--ocv", lg_ocv, "--capacity-ah", "3.0", "--no-hysteresis", "--json", str(mean_curve)]) == 0
    m = json.loads(mean_curve.read_text())
    assert m["rmse_all_pct"] != s["rmse_all_pct"]  # the switch reaches the estimator
    # any start: 25 % into the file from its OCV, with a trace on the file's time base; the paper's c0 method
    trace = tmp_path / "trace.csv"
    later = tmp_path / "later.json"
    assert main(["soc", data, "--ocv", lg_ocv, "--capacity-ah", "3.0", "--start-s", "2500", "--start-soc", "ocv",
                 "--soc-method", "c0", "--trace", str(trace), "--json", str(later)]) == 0
    later_s = json.loads(later.read_text())
    assert later_s["start_s"] == 2500 and later_s["soc_method"] == "c0" and later_s["soc_sigma_end"] is None
    rows = np.genfromtxt(trace, delimiter=",", names=True)
    assert rows.dtype.names[:4] == ("time_s", "soc", "soc_sigma", "soc_reference")
    assert np.isnan(rows["soc"][:2500]).all() and np.isfinite(rows["soc"][2500:]).all()
    assert abs(rows["soc"][2500] - rows["soc_reference"][2500]) < 0.1  # read from the voltage at the start
    assert rows["time_s"][-1] == pytest.approx(len(rows) - 1)
    with pytest.raises(SystemExit) as exc:  # a usage error, named: exit 2, no traceback
        main(["soc", data, "--ocv", lg_ocv, "--capacity-ah", "3.0", "--start-soc", "1.5"])
    assert exc.value.code == 2
    out = tmp_path / "fit.json"
    assert main(["fit", data, "--ocv", lg_ocv, "--capacity-ah", "3.0", "--method", "arx", "--json", str(out)]) == 0
    f = json.loads(out.read_text())
    med = f["median_soc_20_90"]
    assert 0.005 < med["r0_ohm"] < 0.1 and med["tau1_s"] < med["tau2_s"]
    assert f["sim_rmse_mv"] > 0


@pytest.mark.parametrize("content, message", [
    ("time_s,current_a\n0,1\n1,2\n", "voltage_v"),
    ("time_s,current_a,voltage_v\n0,1,3.7\n1,x,3.7\n", "line 3"),
    ("time_s,current_a,voltage_v\n0,1,3.7\n", "row"),
])
def test_bad_data_gives_a_clear_error_and_exit_3(tmp_path, capsys, content, message):
    bad = tmp_path / "bad.csv"
    bad.write_text(content)
    rc = main(["soc", str(bad), "--ocv", PAN_OCV, "--capacity-ah", "2.9"])
    err = capsys.readouterr().err
    assert rc == 3 and "bad.csv" in err and message in err, err  # a data error, not a usage error


def _drive_head(tmp_path, cell: str, cycle: str, seconds: int) -> str:
    """The shipped drive cycle's first ``seconds`` as a recording CSV: for a check that is the tables' or the
    options', not the drive's (a full drive is 2-3 h of estimator time)."""
    from bms_estimator.data import CellRecording, load_recording, save_recording

    rec = load_recording(drive_cycle(cell, cycle))
    k = slice(0, seconds)
    head = CellRecording(rec.time_s[k], rec.current_a[k], rec.voltage_v[k], rec.temperature_c[k])
    return str(save_recording(head, tmp_path / f"{cycle}_head.csv"))


def test_every_command_reads_a_gzipped_ocv_table(tmp_path, capsys):
    """--ocv took .csv only ("not UTF-8 text (invalid start byte at byte 1)") while the recordings take .csv.gz."""
    import gzip

    gz = tmp_path / "ocv.csv.gz"
    gz.write_bytes(gzip.compress(Path(PAN_OCV).read_bytes()))
    data = _drive_head(tmp_path, "panasonic-18650pf", "cycle_1", 900)
    plain_json, gz_json = tmp_path / "plain.json", tmp_path / "gz.json"
    common = ["--capacity-ah", "2.9", "--reference-capacity-ah", "2.9"]
    assert main(["soc", data, "--ocv", PAN_OCV, *common, "--json", str(plain_json)]) == 0
    assert main(["soc", data, "--ocv", str(gz), *common, "--json", str(gz_json)]) == 0, \
        capsys.readouterr().err
    assert json.loads(gz_json.read_text()) == json.loads(plain_json.read_text())


def test_bad_options_are_named(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["soc", "x.csv", "--ocv", PAN_OCV, "--capacity-ah", "-1"])
    assert "--capacity-ah" in capsys.readouterr().err
    rc = main(["soc", str(tmp_path / "missing.csv"), "--ocv", PAN_OCV, "--capacity-ah", "2.9"])
    assert rc == 3 and "missing.csv" in capsys.readouterr().err
    rc = main(["fit", str(drive_cycle("lg-hg2", "la92")), "--ocv", PAN_OCV, "--capacity-ah", "3", "--window", "0"])
    assert rc == 2 and "--window" in capsys.readouterr().err


def test_bench_prints_the_figures(capsys):
    assert main(["bench", "--json", "--seconds", "0.3", "--figures", "cell_updates_per_s,tick_ms_200_cells"]) == 0
    figures = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(figures) == {"cell_updates_per_s", "tick_ms_200_cells"}
    assert figures["cell_updates_per_s"] > 0 and figures["tick_ms_200_cells"] > 0
    assert main(["bench", "--figures", "warp_speed"]) == 2
    assert "--figures: unknown figure(s) warp_speed" in capsys.readouterr().err
    for empty in ("", " , "):  # printed nothing, exit 0
        assert main(["bench", "--figures", empty]) == 2
        assert f"--figures {empty!r} names no figure; choose from cell_updates_per_s" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # printed 'cell_updates_per_s 0.000' with exit 0
        main(["bench", "--figures", "cell_updates_per_s", "--seconds", "0"])
    assert exc.value.code == 2 and "argument --seconds" in capsys.readouterr().err


def test_bench_help_lists_every_figure(capsys):
    """The help's list was a copy that missed six figures the README names (cell_updates_per_s_c0, ...)."""
    from bms_estimator.cli.bench import FIGURES

    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in FIGURES:
        assert name in text, name


def _readme_command_line_section() -> str:
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    return text[text.index("\n## Command line\n"):text.index("\n## SOC from any start")]


def _subcommand_parsers() -> dict:
    import argparse

    from bms_estimator.cli.__main__ import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_every_option_of_every_command_is_in_the_readme_command_line_section():
    """A new user reads the README's Command line section, not 13 --help pages: 47 options of 12
    commands were in no word of it (encode-log --spread/--seed/--t0, dashboard --tls/--password-env,
    soc --reference-ocv, sop-backtest --mode and the cell's current ratings, demo --cell/--plain, ...;
    batch --stack and run --check-config only sections later)."""
    import re

    section = _readme_command_line_section()
    missing = []
    for name, parser in _subcommand_parsers().items():
        for action in parser._actions:
            strings = [o for o in action.option_strings if o not in ("-h", "--help")]
            if strings and not any(re.search(rf"(?<![\w-]){re.escape(o)}(?![\w-])", section) for o in strings):
                missing.append(f"{name} {'/'.join(strings)}")
    assert not missing, missing


def test_every_option_the_readme_command_table_shows_exists():
    """The README's command table is a synopsis: each option it shows for a command is one of its own."""
    import re

    parsers = _subcommand_parsers()
    rows = re.findall(r"^\| `bms-estimator ([a-z-]+) ([^`]*)`", _readme_command_line_section(), re.M)
    assert {name for name, _ in rows} == set(parsers)
    for name, synopsis in rows:
        known = {o for a in parsers[name]._actions for o in a.option_strings}
        for opt in re.findall(r"(?<![\w-])--?[a-z][a-z0-9-]*", synopsis):
            assert opt in known, (name, opt)


def test_compare_on_the_nmc_cell_stays_within_the_bound(tmp_path):
    """LG HG2 udds -> la92 (shipped samples): CT validation simulation RMSE <= 25 mV (11.8 mV when written)."""
    out = tmp_path / "cmp.json"
    assert main(["compare", "--train", str(drive_cycle("lg-hg2", "udds")),
                 "--validate", str(drive_cycle("lg-hg2", "la92")),
                 "--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3.0", "--json", str(out)]) == 0
    m = json.loads(out.read_text())
    assert m["validate"]["lif"]["sim_rmse_mv"] <= 25.0
    assert m["capacity_source"].startswith("output error")
    assert 2.65 < m["capacity_ah_estimated"] < 2.9  # its C/20 discharge gives 2.78 Ah, its end rest 2.81
    assert 2.75 < m["capacity_ah_end_rest"] < 2.85
    prof = m["capacity_profile"]
    assert len(prof["capacity_ah"]) == len(prof["sim_rmse_mv"]) >= 10
    assert m["c0_prior_weight"] == 0.1


EXTENSIONS = ("lif-iv-bv", "lif-iv-ct")


@pytest.fixture(scope="module")
def extensions_compared(tmp_path_factory) -> dict:
    """``compare`` la92 -> udds (shipped LG samples) of both extensions beside lif-iv, in one run: each
    method's validation simulation is its own (compare identifies and simulates per method)."""
    out = tmp_path_factory.mktemp("extensions") / "cmp.json"
    assert main(["compare", "--train", str(drive_cycle("lg-hg2", "la92")), "--validate",
                 str(drive_cycle("lg-hg2", "udds")), "--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3.0",
                 *[a for m in EXTENSIONS for a in ("--method", m)], "--method", "lif-iv", "--json", str(out)]) == 0
    return json.loads(out.read_text())


def _fit_and_compare_lg(tmp_path, method: str, compared: dict) -> tuple[dict, dict]:
    """``fit`` of the shipped LG la92 sample with ``method``, and its ``compare`` la92 -> udds beside lif-iv:
    (the fit's JSON, the compare's); both validation simulations below 30 mV and not the same."""
    out = tmp_path / "fit.json"
    assert main(["fit", str(drive_cycle("lg-hg2", "la92")), "--ocv", str(ocv_table("lg-hg2")), "--capacity-ah",
                 "3.0", "--method", method, "--json", str(out)]) == 0
    f = json.loads(out.read_text())
    assert f["method"] == method and 0 < f["sim_rmse_mv"] < 30
    m = compared
    assert set(m["validate"]) == {*EXTENSIONS, "lif-iv"}
    assert 0 < m["validate"][method]["sim_rmse_mv"] < 30
    assert m["validate"][method]["sim_rmse_mv"] != m["validate"]["lif-iv"]["sim_rmse_mv"]
    return f, m


def test_fit_and_compare_take_the_kinetic_term(tmp_path, capsys, extensions_compared):
    """lif-iv-bv: fit reports K1, K2 and i0; compare simulates the validation file with them."""
    f, _ = _fit_and_compare_lg(tmp_path, "lif-iv-bv", extensions_compared)
    med = f["median_soc_20_90"]
    assert med["i0_a"] == pytest.approx(3.0)
    for j in (1, 2):  # the guard's bound holds in what is reported
        assert abs(med[f"k{j}_ohm"]) <= med[f"r{j}_ohm"]


def test_fit_and_compare_take_the_charge_transfer_branch(tmp_path, capsys, extensions_compared):
    """lif-iv-ct: fit reports the charge-transfer share and V_T; compare simulates the validation file with them."""
    capsys.readouterr()
    f, _ = _fit_and_compare_lg(tmp_path, "lif-iv-ct", extensions_compared)
    assert "charge-transfer fast branch: 100 % of R1" in capsys.readouterr().out
    med = f["median_soc_20_90"]
    assert med["ct_fraction"] == 1.0
    assert med["ct_vt_v"] == pytest.approx(0.05139, abs=1e-5)  # 2RT/F at the default 25 degC


def test_compare_brings_the_resistances_to_the_validation_temperature(tmp_path, capsys):
    """Both shipped LG files log temperature_c: the default corrects, --activation-k 0 does not."""
    common = ["compare", "--train", str(drive_cycle("lg-hg2", "udds")), "--validate",
              str(drive_cycle("lg-hg2", "la92")), "--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3.0",
              "--method", "lif-iv"]
    figs = {}
    for k in ("2500", "0"):
        out = tmp_path / f"cmp_{k}.json"
        assert main([*common, "--activation-k", k, "--json", str(out)]) == 0
        figs[k] = json.loads(out.read_text())["validate"]["lif-iv"]["sim_rmse_mv"]
    assert 0 < figs["2500"] <= 25.0 and 0 < figs["0"] <= 25.0
    assert figs["2500"] != figs["0"]  # the option reaches the validation simulation
    with pytest.raises(SystemExit) as exc:
        main([*common, "--activation-k", "-5"])
    assert exc.value.code == 2 and "--activation-k" in capsys.readouterr().err


def test_a_recording_that_does_not_fit_one_cell_is_a_data_error(tmp_path, capsys):
    """Current in mA (or time in ms) spans 1000 times the stated capacity: every command that takes
    --capacity-ah refuses it (exit 3, the file named) instead of running to nonsense with exit 0."""
    from bms_estimator.data import load_recording

    lg, lg_ocv = drive_cycle("lg-hg2", "la92"), str(ocv_table("lg-hg2"))
    rec = load_recording(lg)
    milliamp = save_recording(CellRecording(rec.time_s, rec.current_a * 1000, rec.voltage_v, rec.temperature_c, "mA"),
                              tmp_path / "milliamp.csv.gz")
    cell = ["--ocv", lg_ocv, "--capacity-ah", "3"]
    for argv in (["soc", str(milliamp)], ["fit", str(milliamp)], ["diagnose", str(milliamp)],
                 ["sop-backtest", str(milliamp)], ["compare", "--train", str(lg), "--validate", str(milliamp)]):
        assert main([*argv, *cell]) == 3, argv
        err = capsys.readouterr().err
        assert "milliamp.csv.gz: its coulomb count spans 2593 Ah, 864.3 times --capacity-ah = 3 Ah" in err, err
    # the stated capacity far from the cell's: too small is seen in the data, too large against the OCV table
    assert main(["fit", str(lg), "--ocv", lg_ocv, "--capacity-ah", "0.3"]) == 3
    assert "la92_1s.csv.gz: its coulomb count spans 2.593 Ah" in capsys.readouterr().err
    assert main(["soc", str(lg), "--ocv", lg_ocv, "--capacity-ah", "3000"]) == 2
    assert ("--capacity-ah 3000 is 1.08e+03 times the C/20 capacity 2.779 Ah of the --ocv table(s) "
            "(lg-hg2_25degC_ocv.csv)") in capsys.readouterr().err


def test_a_recording_too_short_to_estimate_is_a_data_error(tmp_path, capsys):
    short = tmp_path / "short.csv"
    short.write_text("time_s,current_a,voltage_v\n" + "".join(f"{k},-1,3.7\n" for k in range(5)))
    assert main(["fit", str(short), "--ocv", PAN_OCV, "--capacity-ah", "2.9"]) == 3  # the file, not the options
    err = capsys.readouterr().err
    assert "short.csv: only 5 samples after resampling" in err and "time_s in seconds" not in err, err


def test_a_time_column_in_hours_is_named_not_called_a_short_file(tmp_path, capsys):
    """A 3 h drive whose time_s is in hours averaged its 10,984 rows into 4 samples, refused as 'only 4 samples
    after resampling; too short', which sent its user looking for a short file."""
    from bms_estimator.data import load_recording

    rec = load_recording(drive_cycle("panasonic-18650pf", "cycle_1"))
    hours = save_recording(CellRecording(rec.time_s / 3600.0, rec.current_a, rec.voltage_v, rec.temperature_c, "h"),
                           tmp_path / "hours.csv")
    for command in ("fit", "diagnose"):
        assert main([command, str(hours), "--ocv", PAN_OCV, "--capacity-ah", "2.9"]) == 3
        err = capsys.readouterr().err
        assert f"hours.csv: only {int(rec.duration_s // 3600) + 1} samples after resampling" in err, err
        assert (f"its {len(rec):,} rows span only {rec.duration_s / 3600:.4g} s of time_s" in err
                and "is time_s in seconds, not hours or minutes?" in err), err


@pytest.mark.parametrize("argv, option", [
    (["soc", "--reference-capacity-ah", "-1"], "--reference-capacity-ah"),
    (["soc", "--reference-capacity-ah", "nan"], "--reference-capacity-ah"),
    (["soc", "--initial-soc-error", "nan"], "--initial-soc-error"),
    (["soc", "--initial-soc-error", "2"], "--initial-soc-error"),
    (["soc", "--start-soc", "1.5"], "--start-soc"),
    (["fit", "--initial-soc", "5"], "--initial-soc"),
    (["diagnose", "--initial-soc", "-0.1"], "--initial-soc"),
])
def test_soc_and_capacity_options_out_of_range_are_usage_errors(argv, option, capsys):
    """Each ran to 'nan %' or to a reference of -1 Ah with exit 0; now argparse names the option (exit 2)."""
    data = str(drive_cycle("lg-hg2", "la92"))
    with pytest.raises(SystemExit) as exc:
        main([argv[0], data, "--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3", *argv[1:]])
    assert exc.value.code == 2
    assert f"argument {option}" in capsys.readouterr().err


def test_ocv_command_refuses_a_file_that_is_not_a_c20_test(tmp_path, capsys):
    """A drive cycle given to 'ocv' wrote a 48 mV-wide 'OCV table' with exit 0; now it is named as not a C/20
    test (exit 3), as is a test at rest most of the time (HPPC), with the option that reads one."""
    out = tmp_path / "ocv.csv"
    assert main(["ocv", str(drive_cycle("lg-hg2", "la92")), "-o", str(out)]) == 3
    err = capsys.readouterr().err
    assert "la92_1s.csv.gz: not a C/20 test: its longest discharge run removes 0.0612 Ah of the 3.69 Ah" in err, err
    assert not out.exists()
    t = np.arange(3000.0)
    i = np.where((t % 300) < 10, -3.0, 0.0)  # 10 s pulses, rest between: an HPPC-like test
    save_recording(CellRecording(t, i, 3.7 + 0.02 * i, None, "pulses"), tmp_path / "hppc.csv")
    assert main(["ocv", str(tmp_path / "hppc.csv"), "-o", str(out)]) == 3
    err = capsys.readouterr().err
    assert "hppc.csv: the current is zero in 90 % of the samples or more: not a C/20 test" in err
    assert "--hppc-steps" in err


def test_ocv_command_refuses_what_is_not_an_hppc_test_and_a_temperature_off_the_cells_range(tmp_path, capsys):
    """A drive cycle given with --hppc-steps ended in an IndexError traceback (exit 1); --temperature-c 500
    (kelvin?) wrote a table filed at 500 degC with exit 0."""
    out = tmp_path / "ocv.csv"
    t = np.arange(0.0, 4 * 3600.0, 60.0)
    steps = save_recording(CellRecording(t, np.where((t // 1800) % 2 == 0, -0.5, 0.0), 3.9 - 1e-5 * t, None, "s"),
                           tmp_path / "steps.csv")
    assert main(["ocv", str(drive_cycle("lg-hg2", "la92")), "--hppc-steps", str(steps), "-o", str(out)]) == 3
    err = capsys.readouterr().err
    assert "la92_1s.csv.gz with --hppc-steps" in err and "only 0 usable rest point(s)" in err, err
    assert not out.exists()
    for value in ("500", "-300", "nan"):
        with pytest.raises(SystemExit) as exc:
            main(["ocv", str(drive_cycle("lg-hg2", "la92")), "-o", str(out), "--temperature-c", value])
        assert exc.value.code == 2
        assert f"argument --temperature-c: '{value}' is not a cell temperature in degC (-60..150)" in \
            capsys.readouterr().err


def test_commands_that_identify_the_model_refuse_a_file_whose_current_never_moves(tmp_path, capsys):
    """An all-rest file ran through fit, compare, diagnose and sop-backtest with exit 0: diagnose named causes
    'significant' at t = 7.9e14 (a zero noise), sop-backtest printed 'median nan mV'; a constant current gave
    the identifier's prior as the fit. Now exit 3 naming the file; soc still reads a rest file on the OCV."""
    t = np.arange(600.0)
    rest = save_recording(CellRecording(t, np.zeros(t.size), np.full(t.size, 4.1), None, "r"), tmp_path / "rest.csv")
    cc = save_recording(CellRecording(t, np.full(t.size, -1.5), 4.15 - 1e-4 * t, None, "c"), tmp_path / "cc.csv")
    drive = str(drive_cycle("lg-hg2", "la92"))
    cell = ["--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3"]
    for argv, named in ((["fit", str(rest)], rest), (["sop-backtest", str(rest)], rest),
                        (["diagnose", drive, "--validate", str(rest)], rest),
                        (["compare", "--train", drive, "--validate", str(cc)], cc), (["fit", str(cc)], cc)):
        assert main([*argv, *cell]) == 3, argv
        err = capsys.readouterr().err
        what = "at rest throughout (|current| at most 0 A" if named is rest else \
            "at one constant current (within -1.5..-1.5 A"
        assert f"{named}: {what}; the model needs steps of C/100 = 0.03 A of --capacity-ah 3): {argv[0]} " \
            "identifies it from the voltage's response to changes of the current" in err, err
    assert main(["soc", str(rest), *cell, "--reference-capacity-ah", "3", "--start-soc", "ocv"]) == 0


def test_diagnose_on_too_few_samples_names_the_file(tmp_path, capsys):
    """It read 'only 60 samples inside the SOC window -1..2' (exit 2), naming neither the file nor a window
    anyone gave."""
    from bms_estimator.data import load_recording

    rec = load_recording(drive_cycle("lg-hg2", "la92"))
    short = save_recording(CellRecording(rec.time_s[:60], rec.current_a[:60], rec.voltage_v[:60], None, "s"),
                           tmp_path / "short.csv")
    cell = ["--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3"]
    assert main(["diagnose", str(short), *cell]) == 3
    assert f"{short}: only 60 samples; a diagnosis needs 100" in capsys.readouterr().err
    assert main(["diagnose", str(drive_cycle("lg-hg2", "la92")), "--validate", str(short), *cell]) == 3
    assert f"{short}: only 60 samples; a diagnosis needs 100" in capsys.readouterr().err
    assert main(["diagnose", str(drive_cycle("lg-hg2", "la92")), *cell, "--soc-max", "0.05", "--soc-min", "0.01"]) == 3
    assert "la92_1s.csv.gz: only 0 samples with the counted SOC at least 0.01 and at most 0.05; a diagnosis " \
        "needs 100" in capsys.readouterr().err


def test_diagnose_on_a_window_passed_only_at_the_start_names_the_file(capsys):
    """The Panasonic cycle_1 sample (Kollmeyer, CC BY 4.0) is above 0.95 SOC only in its first block, which is
    never scored: numpy's 'Mean of empty slice' warnings, then a ZeroDivisionError traceback."""
    data = str(drive_cycle("panasonic-18650pf", "cycle_1"))
    for soc_min, soc_max, window in (("0.95", "0.99", "at least 0.95 and at most 0.99"), ("0.97", "1.0", "at least 0.97")):
        assert main(["diagnose", data, "--ocv", PAN_OCV, "--capacity-ah", "2.9", "--soc-min", soc_min,
                     "--soc-max", soc_max, "--no-lif"]) == 3
        err = capsys.readouterr().err
        assert err.startswith(f"bms-estimator diagnose: error: {data}: only 0 samples with the counted SOC {window} "
                              "after the first "), err
        assert err.endswith("to score; a diagnosis needs 100\n") and err.count("\n") == 1, err


def test_short_files_and_late_starts_print_figures_not_nan(tmp_path, capsys, monkeypatch):
    """5 min of the LG drive (shipped sample, Kollmeyer, CC BY 4.0) never enters 20-90 % SOC: fit printed no
    parameters and 'simulation RMSE nan mV', compare a table of 'nan', both with the capacity at the low end of
    its search (0.8 x 3 Ah) as if estimated; soc from the last minute printed 'SOC RMSE nan %'. Now the
    figures are over the whole file (said so, in the plot's error panel too, which was empty), the capacity's
    search end is warned about, and the JSON keeps null for the figures that do not exist."""
    from bms_estimator.data import load_recording

    la92 = str(drive_cycle("lg-hg2", "la92"))
    rec = load_recording(la92)
    short = save_recording(CellRecording(rec.time_s[:300], rec.current_a[:300], rec.voltage_v[:300],
                                         rec.temperature_c[:300], "s"), tmp_path / "short.csv")
    cell = ["--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3"]
    end = (f"{short}: the effective capacity 2.400 Ah is the low end of its search (0.8..1.1 x --capacity-ah 3): "
           "the file does not identify it")
    import bms_estimator.plots as plots

    shown = {}
    real_save = plots.save_figure

    def save(fig, path, note=None, **kw):  # what the error panel plots, per figure
        shown[Path(path).name] = (fig._suptitle.get_text(), [np.isfinite(line.get_ydata()).sum()
                                                              for line in fig.axes[1].get_lines()])
        return real_save(fig, path, note, **kw)

    monkeypatch.setattr(plots, "save_figure", save)
    assert main(["fit", str(short), *cell, "--json", str(tmp_path / "fit.json"), "--plot", str(tmp_path / "fit.png")]) == 0
    monkeypatch.undo()
    title, finite = shown["fit_simulation.png"]  # the error panel was empty (every sample masked out)
    assert title.endswith("(whole file: none of it in the SOC window)") and finite == [300], shown
    res = capsys.readouterr()
    assert end in res.err and "nan" not in res.out, res
    assert "(final values: the counted SOC, 0.98..1.00, has no identified sample in 20-90 %)" in res.out
    assert " mV over the whole file; capacity 2.400 Ah" in res.out
    fit = json.loads((tmp_path / "fit.json").read_text())
    assert fit["sim_rmse_mv"] is None and fit["sim_rmse_mv_full_range"] > 0
    assert main(["compare", "--train", str(short), "--validate", str(short), *cell, "--method", "arx"]) == 0
    res = capsys.readouterr()
    assert end in res.err and "nan" not in res.out, res
    assert res.out.count("(whole file: its counted SOC never enters the window)") == 2
    assert main(["fit", la92, *cell]) == 0  # a whole drive: its capacity inside the search, no warning
    assert "end of its search" not in capsys.readouterr().err
    last = tmp_path / "last.json"
    assert main(["soc", la92, *cell, "--start-s", str(rec.time_s[-40]), "--json", str(last)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("SOC RMSE ") and "% from the start (the recording ends 39 s after it" in out, out
    assert "nan" not in out
    figs = json.loads(last.read_text())
    assert figs["rmse_30min_pct"] is None and figs["rmse_all_pct"] >= 0


def test_a_recording_far_from_the_tables_temperatures_is_warned_about(tmp_path, capsys):
    """The OCV surface holds its end tables outside their temperatures: the LG 0 degC drives read on the
    25 degC table alone ran to SOC RMSE 2.7-3.7 % (0.7-1.9 % on their own table) with exit 0 and no word.
    The shipped sample at its own ambient (24 degC, table 23.9) is not warned about."""
    from bms_estimator.data import load_recording

    la92 = str(drive_cycle("lg-hg2", "la92"))
    rec = load_recording(la92)
    cold = save_recording(CellRecording(rec.time_s, rec.current_a, rec.voltage_v, rec.temperature_c - 30.0, "c"),
                          tmp_path / "cold.csv.gz")
    cell = ["--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3"]
    assert main(["soc", str(cold), *cell, "--reference-capacity-ah", "2.8"]) == 0
    err = capsys.readouterr().err
    assert (f"bms-estimator soc: warning: {cold}: its median cell temperature -5.8 degC is 30 K outside the --ocv "
            "table(s) at 23.9 degC, read there (held, not extrapolated): give a table measured near -6 degC") in err
    assert main(["soc", la92, *cell]) == 0
    assert "outside the --ocv table" not in capsys.readouterr().err


def test_a_recording_just_below_zero_is_told_to_take_a_table_near_0_not_minus_0_degc(tmp_path, capsys):
    """The LG 0 degC udds drive (median cell temperature -0.3 degC) on the 25 degC table alone was told to
    'give a table measured near -0 degC': the rounded temperature kept the sign of the unrounded one."""
    from bms_estimator.data import load_recording

    rec = load_recording(str(drive_cycle("lg-hg2", "la92")))
    shift = float(np.median(rec.temperature_c)) + 0.3  # the median lands at -0.3 degC
    cold = save_recording(CellRecording(rec.time_s, rec.current_a, rec.voltage_v, rec.temperature_c - shift, "c"),
                          tmp_path / "cold.csv.gz")
    assert main(["soc", str(cold), "--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3",
                 "--reference-capacity-ah", "2.8"]) == 0
    err = capsys.readouterr().err
    assert "its median cell temperature -0.3 degC is 24 K outside" in err
    assert "give a table measured near 0 degC" in err, err


def test_compare_of_files_at_different_periods_names_them_and_the_way_out(tmp_path, nmc_like_ocv, capsys):
    """It read 'training and validation files have different sample periods (60.0 vs 1.0 s)'."""
    c20 = tmp_path / "c20.csv"
    _c20_file(c20, nmc_like_ocv)  # logged every 60 s
    la92 = str(drive_cycle("lg-hg2", "la92"))
    assert main(["compare", "--train", str(c20), "--validate", la92, "--ocv", str(ocv_table("lg-hg2")),
                 "--capacity-ah", "3"]) == 2
    assert (f"--train {c20} is sampled every 60 s, --validate {la92} every 1 s: give --resample-s 60 to average "
            "both to one period") in capsys.readouterr().err


def test_soc_without_a_table_at_the_recordings_ambient_names_its_temperature_plainly(tmp_path, capsys):
    """The message read 'the recording's 2.011000000013155 degC'."""
    from bms_estimator.data import load_recording

    rec = load_recording(drive_cycle("lg-hg2", "la92"))
    cold = save_recording(CellRecording(rec.time_s, rec.current_a, rec.voltage_v, rec.temperature_c - 22.123456789,
                                        "cold"), tmp_path / "cold.csv.gz")
    assert main(["soc", str(cold), "--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3"]) == 2
    err = capsys.readouterr().err
    assert "no C/20 table (with hysteresis) within 5 K of the recording's 2.1 degC among --ocv" in err, err


def test_soc_on_a_file_without_a_discharge_names_the_file_and_the_way_out(tmp_path, capsys):
    """A charge-only recording read 'the recording has no net discharge: no capacity to measure' (exit 2),
    naming neither the file nor --reference-capacity-ah."""
    from bms_estimator.data import load_recording

    rec = load_recording(drive_cycle("lg-hg2", "la92"))
    n = 1200
    t = np.arange(n, dtype=float)
    i = np.r_[np.full(n - 300, 1.5), np.zeros(300)]  # a C/2 charge from 20 % SOC, then 300 s of rest
    v = 3.55 + 0.5 * t / n + 0.03 * i
    save_recording(CellRecording(t, i, v, rec.temperature_c[:n], "charge"), tmp_path / "charge.csv")
    assert main(["soc", str(tmp_path / "charge.csv"), "--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3"]) == 3
    err = capsys.readouterr().err
    assert "charge.csv: no SOC reference from the file: the recording has no net discharge" in err, err
    assert "--reference-capacity-ah" in err
    # a file that ends under load: the same, naming the file (it read 'the recording ends with 0 s of rest')
    save_recording(CellRecording(t[:600], -i[:600], v[::-1][:600], None, "load"), tmp_path / "load.csv")
    assert main(["soc", str(tmp_path / "load.csv"), "--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3"]) == 3
    assert "load.csv: no SOC reference from the file: the recording ends with 0 s of rest" in capsys.readouterr().err


def test_a_file_that_does_not_start_at_initial_soc_is_warned_about(tmp_path, capsys):
    """--initial-soc defaults to 1.0 (the data set's full starts); a file starting at rest half full ran to a
    wrong capacity without a word. The measured sample starting full gets no warning."""
    from bms_estimator.core.ecm import EcmParams, simulate_ecm

    lg_ocv = str(ocv_table("lg-hg2"))
    curve = read_ocv_table(lg_ocv)
    i = np.r_[np.zeros(120), np.tile(np.r_[np.full(60, -3.0), np.zeros(60), np.full(20, 1.5), np.zeros(40)], 8)]
    sim = simulate_ecm(i, 1.0, EcmParams.from_rc(0.02, [0.01, 0.02], [10.0, 200.0]), curve.ocv, soc0=0.5,
                       capacity_ah=3.0)
    half = save_recording(CellRecording(np.arange(len(i), dtype=float), i, sim.voltage_v, None, "half"),
                          tmp_path / "half.csv")
    assert main(["fit", str(half), "--ocv", lg_ocv, "--capacity-ah", "3", "--method", "arx"]) == 0
    err = capsys.readouterr().err
    assert "half.csv: its first voltage" in err and "reads SOC 0.50 on the --ocv table, not --initial-soc 1" in err
    assert main(["fit", str(half), "--ocv", lg_ocv, "--capacity-ah", "3", "--method", "arx",
                 "--initial-soc", "0.5"]) == 0
    assert "first voltage" not in capsys.readouterr().err
    assert main(["fit", str(drive_cycle("lg-hg2", "la92")), "--ocv", lg_ocv, "--capacity-ah", "3",
                 "--method", "arx"]) == 0
    assert "first voltage" not in capsys.readouterr().err


def test_soc_warns_when_the_capacity_ends_at_its_bound(tmp_path, capsys):
    """--capacity-ah 5.8 for the 2.9 Ah Panasonic cell (shipped sample, Kollmeyer, CC BY 4.0; twice the table's
    capacity, the most the command accepts): the capacity estimate ends at its low bound, 0.6 x 5.8 Ah, and the
    run says so on stderr and in its JSON; with 2.9 Ah it does not."""
    data = str(drive_cycle("panasonic-18650pf", "cycle_1"))
    wrong, right = tmp_path / "wrong.json", tmp_path / "right.json"
    assert main(["soc", data, "--ocv", PAN_OCV, "--capacity-ah", "5.8", "--start-soc", "ocv", "--json", str(wrong)]) == 0
    err = capsys.readouterr().err
    assert ("bms-estimator soc: warning: the capacity estimate ended at its low bound, 0.6 x --capacity-ah 5.8 = "
            "3.480 Ah") in err and "--capacity-ah is likely wrong for this cell" in err, err
    assert err.count("capacity estimate ended at its") == 1
    s = json.loads(wrong.read_text())
    assert s["capacity_at_bound"] == -1 and s["capacity_ah_estimated"] == pytest.approx(0.6 * 5.8)
    assert main(["soc", data, "--ocv", PAN_OCV, "--capacity-ah", "2.9", "--start-soc", "ocv", "--json", str(right)]) == 0
    assert "capacity estimate ended" not in capsys.readouterr().err
    assert json.loads(right.read_text())["capacity_at_bound"] == 0


def test_sop_backtest_refuses_voltage_limits_outside_the_cells_range(capsys):
    """--v-min 5 ran to a back-test in which every window broke a limit no cell can keep."""
    drive = str(drive_cycle("panasonic-18650pf", "cycle_1"))
    cell = ["--ocv", str(ocv_table("panasonic-18650pf")), "--capacity-ah", "2.9"]
    assert main(["sop-backtest", drive, *cell, "--v-min", "5", "--v-max", "6"]) == 2
    err = capsys.readouterr().err
    assert "--v-min 5 V / --v-max 6 V leave no room inside the --ocv tables' OCV range" in err, err
    assert main(["sop-backtest", drive, *cell, "--v-min", "1", "--v-max", "2"]) == 2
    assert "leave no room" in capsys.readouterr().err


def test_replay_and_batch_name_a_directory_given_as_a_log(tmp_path, capsys):
    """A directory read 'no such log file'."""
    from bms_estimator.errors import DataError
    from bms_estimator.fleet.frames import read_frames

    assert main(["replay", str(tmp_path), "--interface", "virtual", "--channel", "x"]) == 2
    assert f"{tmp_path}: a directory, not a log file" in capsys.readouterr().err
    with pytest.raises(DataError, match="a directory, not a log file"):
        read_frames(tmp_path)


def test_a_tuning_option_out_of_bounds_is_named_as_the_option(capsys):
    """The config's bound named its field ('forgetting must be ...'), not the option the user typed."""
    cell = ["--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3"]
    drive = str(drive_cycle("lg-hg2", "la92"))
    for option, value, said in (("--forgetting", "1.5", "--forgetting must be a finite number >= 0.9 and <= 1, got 1.5"),
                                ("--tau-max-s", "-3", "--tau-max-s must be a finite number > 0, got -3"),
                                ("--error-on-mv", "-5", "--error-on-mv must be a finite number >= 0, got -5")):
        assert main(["soc", drive, *cell, option, value]) == 2
        assert said in capsys.readouterr().err


def test_adaptation_thresholds_are_used_as_given_or_refused_naming_both(capsys):
    """--error-off-mv was clamped to --error-on-mv (min of the two) and both defaulted to 0, so that
    '--error-on-mv 50' alone (adaptation never turns off) and '--error-off-mv 5' alone (clamped to 0) gave
    the default result without a word."""
    from bms_estimator.cli.__main__ import build_parser
    from bms_estimator.cli.common import soc_config

    cell = ["--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3"]
    drive = str(drive_cycle("lg-hg2", "la92"))
    for command in ("soc", "fit", "sop-backtest"):
        args = build_parser(command).parse_args([command, drive, *cell, "--error-on-mv", "3", "--error-off-mv", "1.5"])
        ident = soc_config(args).identifier
        assert (ident.error_on_v, ident.error_off_v) == pytest.approx((0.003, 0.0015))
        args = build_parser(command).parse_args([command, drive, *cell])
        assert (soc_config(args).identifier.error_on_v, soc_config(args).identifier.error_off_v) == (0.0, 0.0)
    for options, said in (
            (["--error-on-mv", "50"], "--error-on-mv 50 with --error-off-mv 0 (the default) changes nothing: "
                                      "adaptation starts on and never turns off below 0 mV"),
            (["--error-off-mv", "5"], "--error-off-mv 5 is above --error-on-mv 0 (the default)"),
            (["--error-on-mv", "3", "--error-off-mv", "5"], "--error-off-mv 5 is above --error-on-mv 3")):
        assert main(["soc", drive, *cell, *options]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"bms-estimator soc: error: {said}") and err.count("\n") == 1, err


def test_soc_c0_warns_when_the_voltage_says_the_stated_capacity_is_5x_the_cells(tmp_path, capsys):
    """--soc-method c0 with an OCV table without capacity_ah (nothing to compare --capacity-ah with up front) and
    --capacity-ah 5x the LG HG2 cell's (shipped udds sample, Kollmeyer et al., CC BY 4.0): the c0 voltage line reads
    about 2.6 Ah, and the run says so once on stderr (the file, the figure) and in its JSON; stated right it does not."""
    table = tmp_path / "no_capacity.csv"
    ocv_csv = Path(str(ocv_table("lg-hg2")))
    lines = ocv_csv.read_text().splitlines()
    cols = lines[0].split(",")
    keep = [k for k, c in enumerate(cols) if c != "capacity_ah"]
    table.write_text("\n".join(",".join(r.split(",")[k] for k in keep) for r in lines) + "\n")
    data = str(drive_cycle("lg-hg2", "udds"))
    wrong, right = tmp_path / "wrong.json", tmp_path / "right.json"
    assert main(["soc", data, "--ocv", str(table), "--capacity-ah", "14", "--soc-method", "c0",
                 "--json", str(wrong)]) == 0
    err = capsys.readouterr().err
    assert err.count("warning:") == 1, err
    assert "the voltage says this cell's capacity is about 2." in err and "--capacity-ah 14 is" in err, err
    assert Path(data).name in err
    s = json.loads(wrong.read_text())
    assert s["capacity_at_bound"] == -1 and 2.3 < s["capacity_ah_voltage_line"] < 3.0
    assert main(["soc", data, "--ocv", str(table), "--capacity-ah", "2.8", "--soc-method", "c0",
                 "--json", str(right)]) == 0
    assert "warning" not in capsys.readouterr().err
    s = json.loads(right.read_text())
    assert s["capacity_at_bound"] == 0 and 2.3 < s["capacity_ah_voltage_line"] < 3.0


def test_ocv_tables_of_two_cells_are_named_in_one_warning(tmp_path, capsys):
    """--ocv given the LG HG2 table and the Panasonic 18650PF one labelled 20 degC (shipped samples, Kollmeyer,
    CC BY 4.0): the surface blends two cells; one warning line names both files, their temperatures and the
    figure (not refused: core.ocv_surface, item 9). The LG table with a copy of itself 20 K colder says nothing."""
    pan = read_ocv_table(PAN_OCV)
    pan20 = write_ocv_table(OcvCurve(pan.soc, pan.ocv_v, pan.hysteresis_v, temperature_c=20.0), tmp_path / "pan20.csv")
    data = _drive_head(tmp_path, "lg-hg2", "udds", 600)  # its first 10 min: the warning is the tables'
    out = tmp_path / "mixed.json"
    assert main(["soc", data, "--ocv", str(ocv_table("lg-hg2")), "--ocv", str(pan20), "--capacity-ah", "2.8",
                 "--reference-capacity-ah", "2.8", "--json", str(out)]) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err
    line = [w for w in err.splitlines() if "not tables of one cell" in w or "tables of one cell?" in w]
    assert len(line) == 1, err
    assert line[0].startswith("bms-estimator soc: warning: --ocv: ") and "pan20.csv (20 degC) and " in line[0], err
    assert "lg-hg2_25degC_ocv.csv (23.871 degC) differ by 4" in line[0], err
    lg = read_ocv_table(ocv_table("lg-hg2"))
    lg5 = write_ocv_table(OcvCurve(lg.soc, lg.ocv_v, lg.hysteresis_v, temperature_c=4.0), tmp_path / "lg4.csv")
    assert main(["soc", data, "--ocv", str(ocv_table("lg-hg2")), "--ocv", str(lg5), "--capacity-ah", "2.8",
                 "--reference-capacity-ah", "2.8", "--json", str(out)]) == 0
    assert "tables of one cell" not in capsys.readouterr().err


def test_python_dash_m_runs_the_command_line():
    """``python -m bms_estimator`` is the command where the console script is not on PATH (a venv not
    activated, a systemd unit naming the interpreter); before, it said 'No module named bms_estimator.__main__'."""
    import subprocess
    import sys

    from bms_estimator import package_version

    out = subprocess.run([sys.executable, "-m", "bms_estimator", "--version"], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert package_version() in out.stdout
    bad = subprocess.run([sys.executable, "-m", "bms_estimator", "no-such-command"], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and "bms-estimator: error:" in bad.stderr and "Traceback" not in bad.stderr


def test_a_file_the_identifier_never_starts_on_says_its_figures_are_the_prior(tmp_path, capsys):
    """The Panasonic cycle_1 drive logged every 10 s: no identified sample, and fit printed the identifier's prior as
    'final values: the counted SOC, -0.00..1.00, has no identified sample in 20-90 %', compare three identical
    rows (LIF-IV, LIF and ARX), without a word; the same drive's first 20 min at 1 s identify (no warning)."""
    from bms_estimator.data import load_recording

    rec = load_recording(drive_cycle("panasonic-18650pf", "cycle_1"))
    every10 = save_recording(CellRecording(rec.time_s[::10], rec.current_a[::10], rec.voltage_v[::10],
                                           rec.temperature_c[::10], "10 s"), tmp_path / "every10.csv")
    out_json = tmp_path / "fit.json"
    assert main(["fit", str(every10), "--ocv", PAN_OCV, "--capacity-ah", "2.9", "--json", str(out_json)]) == 0
    out, err = capsys.readouterr()
    assert "(nothing identified: the identifier's prior)" in out and "has no identified sample" not in out, out
    assert "every10.csv: lif-iv identified no sample of its 1099 (3.1 h at 10 s)" in err, err
    assert main(["compare", "--train", str(every10), "--validate", str(every10), "--ocv", PAN_OCV, "--capacity-ah",
                 "2.9", "--method", "lif", "--method", "arx", "--json", str(out_json)]) == 0
    err = capsys.readouterr().err
    assert "every10.csv: lif and arx identified no sample of its 1099" in err, err
    assert [m["identified"] for m in json.loads(out_json.read_text())["train"].values()] == [False, False]
    k = rec.time_s < 1200
    first = save_recording(CellRecording(rec.time_s[k], rec.current_a[k], rec.voltage_v[k], rec.temperature_c[k],
                                         "20 min"), tmp_path / "first20.csv")
    assert main(["compare", "--train", str(first), "--validate", str(first), "--ocv", PAN_OCV, "--capacity-ah",
                 "2.9", "--method", "lif", "--json", str(out_json)]) == 0
    assert "identified no sample" not in capsys.readouterr().err
    assert json.loads(out_json.read_text())["train"]["lif"]["identified"] is True
