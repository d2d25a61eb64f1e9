"""Output options, checked before a command reads or computes anything (``bms_estimator/cli/outputs.py``): an
output that is an input, in a missing directory, of the wrong kind or in a format matplotlib cannot write is
a usage error (exit 2) naming the option and the path, and nothing is written or made."""

from __future__ import annotations

import os
import shutil

import pytest

from bms_estimator.cli.__main__ import main
from bms_estimator.cli.outputs import check_outputs, figure_output, file_output, folder_output
from bms_estimator.errors import EXIT_USAGE, UsageError
from bms_estimator.samples import drive_cycle, ocv_table



@pytest.fixture(autouse=True)
def no_recording_read(monkeypatch):
    """A refused command has not read its data: reading a recording here fails the command (the output check
    comes first, before the 5-40 s the full runs take)."""
    def read(path):
        raise AssertionError(f"{path} was read before the output check")

    monkeypatch.setattr("bms_estimator.data._read_text", read)


@pytest.fixture
def files(tmp_path):
    """Copies of a shipped drive cycle and OCV table (LG HG2, Kollmeyer et al., CC BY 4.0) to overwrite."""
    data = tmp_path / "data.csv.gz"
    table = tmp_path / "t.csv"
    shutil.copy(drive_cycle("lg-hg2", "la92"), data)
    shutil.copy(ocv_table("lg-hg2"), table)
    return data, table


def _refused(argv: list[str], capsys) -> str:
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == EXIT_USAGE, err
    assert "Traceback" not in err, err
    last = err.strip().splitlines()[-1]  # (batch's configuration check may warn before)
    assert last.startswith(f"bms-estimator {argv[0]}: error: ") and (argv[0] == "batch" or err.count("\n") == 1), err
    return last


def test_an_output_that_is_an_input_is_refused_and_the_input_kept(files, capsys):
    """'ocv c20.csv -o c20.csv' overwrote the measured test; --trace/--json on a data or table file likewise."""
    data, table = files
    cell = ["--ocv", str(table), "--capacity-ah", "3"]
    before = {p: p.read_bytes() for p in files}
    for argv, option, named in (
            (["ocv", str(data), "-o", str(data)], "-o/--output", f"the input DATA {data}"),
            (["soc", str(data), *cell, "--trace", str(data)], "--trace", f"the input DATA {data}"),
            (["soc", str(data), *cell, "--json", str(table)], "--json", f"the input --ocv {table}"),
            (["sop-backtest", str(data), *cell, "--json", str(data)], "--json", f"the input DATA {data}"),
            (["diagnose", str(data), *cell, "--json", str(data)], "--json", f"the input DATA {data}"),
            (["fit", str(data), *cell, "--json", str(table)], "--json", f"the input --ocv {table}"),
            (["compare", "--train", str(data), "--validate", str(data), *cell, "--json", str(data)], "--json",
             f"the input --train {data}"),
            (["encode-log", str(data), "--cells", "2", "-o", str(table.with_suffix("")) + ".log",
              "--ocv", str(table.with_suffix("")) + ".log.truth.json"], "-o/--output", "(it writes ")):
        if argv[0] == "encode-log":
            shutil.copy(table, argv[-1])  # the truth sidecar's name given as the OCV table
        err = _refused(argv, capsys)
        assert err.startswith(f"bms-estimator {argv[0]}: error: {option} ") and named in err, err
        assert "writing it would overwrite the input; give another path" in err, err
    assert {p: p.read_bytes() for p in files} == before


def test_an_input_reached_through_another_path_is_the_same_file(files, capsys, monkeypatch):
    """A relative path, a symbolic link and a hard link to the input are the input."""
    data, table = files
    monkeypatch.chdir(data.parent)
    link = data.parent / "link.csv.gz"
    link.symlink_to(data)
    hard = data.parent / "hard.csv.gz"
    os.link(data, hard)
    cell = ["--ocv", str(table), "--capacity-ah", "3"]
    for out in ("data.csv.gz", "./data.csv.gz", str(link), str(hard)):
        err = _refused(["soc", str(data), *cell, "--json", out], capsys)
        assert f"--json {os.path.normpath(out)} is the input DATA {data}" in err, err


def test_two_outputs_that_are_one_file_are_refused(files, capsys):
    data, table = files
    out = data.parent / "x.out"
    err = _refused(["soc", str(data), "--ocv", str(table), "--capacity-ah", "3", "--trace", str(out),
                    "--json", str(out)], capsys)
    assert f"--json {out} is also written by --trace: one would overwrite the other" in err, err
    # fit --plot writes a second figure beside the first, X_simulation.png
    sim = data.parent / "p_simulation.png"
    err = _refused(["fit", str(data), "--ocv", str(table), "--capacity-ah", "3", "--json", str(sim),
                    "--plot", str(data.parent / "p.png")], capsys)
    assert f"--plot {data.parent / 'p.png'} (it writes {sim}) is also written by --json" in err, err


def test_an_output_in_a_missing_directory_is_refused_and_nothing_made(files, capsys):
    """encode-log -o /nonexistdir/x.log made /nonexistdir at the filesystem root; fit --plot nodir/x.png and
    --json nodir2/x.json made their folders; the folder options made their parents."""
    data, table = files
    root = data.parent
    cell = ["--ocv", str(table), "--capacity-ah", "3"]
    for argv, option in (
            (["ocv", str(data), "-o", str(root / "nodir" / "x.csv")], "-o/--output"),
            (["fit", str(data), *cell, "--plot", str(root / "nodir" / "x.png")], "--plot"),
            (["fit", str(data), *cell, "--json", str(root / "nodir" / "x.json")], "--json"),
            (["soc", str(data), *cell, "--trace", str(root / "nodir" / "x.csv")], "--trace"),
            (["sop-backtest", str(data), *cell, "--json", str(root / "nodir" / "x.json")], "--json"),
            (["encode-log", str(data), "--cells", "2", "-o", str(root / "nodir" / "x.log")], "-o/--output"),
            (["compare", "--train", str(data), "--validate", str(data), *cell, "--plots", str(root / "nodir" / "p")],
             "--plots"),
            (["diagnose", str(data), *cell, "--report", str(root / "nodir" / "deeper" / "r")], "--report"),
            (["demo", "--output", str(root / "nodir" / "d")], "--output"),
            (["batch", str(data), "--config", str(table), "--out", str(root / "nodir" / "b")], "--out")):
        if argv[0] == "batch":  # (its configuration is checked first: give it one)
            cfg = root / "c.toml"
            cfg.write_text('[can]\ninterface = "virtual"\nchannel = "x"\n')
            argv[argv.index("--config") + 1] = str(cfg)
        err = _refused(argv, capsys)
        assert f"error: {option} {root / 'nodir'}" in err, err
        assert f"the directory {root / 'nodir'} does not exist; give a path in an existing directory" in err, err
        assert not (root / "nodir").exists()
    afile = root / "afile"
    afile.write_text("x")
    err = _refused(["encode-log", str(data), "--cells", "2", "-o", str(afile / "x.log")], capsys)
    assert f"-o/--output {afile / 'x.log'}: the directory {afile} is a file, not a directory" in err, err


def test_a_folder_option_given_a_file_and_a_file_option_given_a_folder_are_refused(files, capsys):
    """demo --output, compare --plots and diagnose --report on an existing file read 'FileExistsError: [Errno 17]',
    exit 1 (after the whole run, for compare and diagnose)."""
    data, table = files
    cell = ["--ocv", str(table), "--capacity-ah", "3"]
    afile = data.parent / "afile"
    afile.write_text("keep")
    for argv, option in ((["demo", "--output", str(afile)], "--output"),
                         (["compare", "--train", str(data), "--validate", str(data), *cell, "--plots", str(afile)],
                          "--plots"),
                         (["diagnose", str(data), *cell, "--report", str(afile)], "--report")):
        err = _refused(argv, capsys)
        assert f"error: {option} {afile}: exists and is not a directory" in err, err
    assert afile.read_text() == "keep"
    err = _refused(["soc", str(data), *cell, "--json", str(data.parent)], capsys)
    assert f"error: --json {data.parent}: is a directory; give a file name" in err, err


def test_a_figure_format_matplotlib_cannot_write_is_refused_before_the_fit(files, capsys):
    """fit --plot out.xyz failed with matplotlib's "Format 'xyz' is not supported" after the whole fit."""
    data, table = files
    cell = ["--ocv", str(table), "--capacity-ah", "3"]
    out = data.parent / "out.xyz"
    for command in ("fit", "soc"):
        err = _refused([command, str(data), *cell, "--plot", str(out)], capsys)
        assert f"error: --plot {out}: matplotlib cannot write a '.xyz' figure; give a file ending in " in err, err
        assert ".png" in err and ".pdf" in err
    assert not out.exists()


def test_the_check_passes_what_the_commands_may_write(tmp_path):
    """Not given, '-' for standard output, a new file in an existing folder, a folder to make in one, a
    figure without a suffix (matplotlib writes X.png) or in another case (.PNG)."""
    data = tmp_path / "d.csv"
    data.write_text("x")
    check_outputs([("DATA", data), ("--ocv", [data, None]), ("--hppc-steps", None)],
                  [file_output("--json", None), file_output("--json", "-", stdout=True),
                   file_output("--trace", tmp_path / "t.csv"), folder_output("--plots", tmp_path / "new", "a.png"),
                   figure_output("--plot", tmp_path / "f.PNG")])
    fig = figure_output("--plot", tmp_path / "fig", "{stem}_simulation.png")
    assert fig.writes == (tmp_path / "fig.png", tmp_path / "fig_simulation.png")
    with pytest.raises(UsageError, match="--plot .* is the input DATA"):
        check_outputs([("DATA", tmp_path / "d.png")], [figure_output("--plot", tmp_path / "d")])
    with pytest.raises(UsageError, match="--plots .* is the input DATA"):
        check_outputs([("DATA", tmp_path / "new" / "a.png")], [folder_output("--plots", tmp_path / "new", "a.png")])


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc, a directory no one can write in")
def test_an_output_where_nothing_can_be_written_is_refused_before_the_run(files, capsys):
    """fit --json /proc/x.json, diagnose --report /proc/r, ocv -o /proc/o.csv ran the whole command and then failed
    with exit 3, "/proc/x.json: No such file or directory" (no option named, the result lost)."""
    data, table = files
    cell = ["--ocv", str(table), "--capacity-ah", "3"]
    for argv, option, path in (
            (["fit", str(data), *cell, "--json", "/proc/x.json"], "--json", "/proc/x.json"),
            (["fit", str(data), *cell, "--plot", "/proc/x.png"], "--plot", "/proc/x.png"),
            (["ocv", str(data), "-o", "/proc/o.csv"], "-o/--output", "/proc/o.csv"),
            (["soc", str(data), *cell, "--trace", "/proc/t.csv"], "--trace", "/proc/t.csv"),
            (["compare", "--train", str(data), "--validate", str(data), *cell, "--plots", "/proc/p"], "--plots",
             "/proc/p"),
            (["diagnose", str(data), *cell, "--report", "/proc/r"], "--report", "/proc/r")):
        err = _refused(argv, capsys)
        assert f"error: {option} {path}: cannot write in the directory /proc" in err, err


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root writes in a read-only directory")
def test_an_output_in_a_read_only_directory_is_refused_before_the_run(files, capsys):
    data, table = files
    locked = data.parent / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        err = _refused(["diagnose", str(data), "--ocv", str(table), "--capacity-ah", "3", "--json",
                        str(locked / "x.json")], capsys)
    finally:
        locked.chmod(0o755)
    assert f"error: --json {locked / 'x.json'}: cannot write in the directory {locked}" in err, err
