"""Command-line conventions: --version, python-can's bus options and configuration, one-line
errors, and exit codes that tell usage, data and runtime errors apart."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import can
import pytest

from bms_estimator import package_version
from bms_estimator.cli.__main__ import main
from bms_estimator.errors import EXIT_DATA, EXIT_RUNTIME, EXIT_USAGE

REPO = Path(__file__).resolve().parents[1]


def _cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bms_estimator.cli", *args], capture_output=True, text=True,
                          timeout=120, cwd=REPO, env=env)


def _small_log(tmp_path: Path) -> Path:
    path = tmp_path / "x.log"
    with can.Logger(str(path)) as w:
        for k in range(20):
            w.on_message_received(can.Message(timestamp=1.0 + 0.01 * k, arbitration_id=0x100 + k, data=bytes([k])))
    return path


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"bms-estimator {package_version()}"


def test_replay_takes_python_cans_bus_options_and_configuration(tmp_path, monkeypatch):
    log = _small_log(tmp_path)
    ch = f"cli-{tmp_path.name}"
    rx = can.Bus(interface="virtual", channel=ch)
    try:
        # -i/-c as python-can's own tools spell them
        assert main(["replay", str(log), "-i", "virtual", "-c", ch, "--speed", "max", "--no-progress"]) == 0
        got = [rx.recv(1.0) for _ in range(20)]
        assert [m.arbitration_id for m in got] == [0x100 + k for k in range(20)]
        # nothing on the command line: python-can's configuration ($CAN_INTERFACE, $CAN_CHANNEL, ~/.canrc)
        monkeypatch.setenv("CAN_INTERFACE", "virtual")
        monkeypatch.setenv("CAN_CHANNEL", ch)
        assert main(["replay", str(log), "--speed", "max", "--no-progress"]) == 0
        assert rx.recv(1.0).arbitration_id == 0x100
    finally:
        rx.shutdown()


def test_can_errors_are_one_line_with_their_exit_codes(tmp_path):
    log = _small_log(tmp_path)
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}  # no ~/.canrc, no CAN_* variables
    # an interface python-can does not know: a usage error (argparse lists the choices)
    res = _cli("replay", str(log), "-i", "nosuchinterface", env=env)
    assert res.returncode == EXIT_USAGE and "Traceback" not in res.stderr
    assert "invalid choice: 'nosuchinterface'" in res.stderr
    # no interface anywhere
    res = _cli("replay", str(log), env=env)
    assert res.returncode == EXIT_USAGE and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines()[-1].startswith("bms-estimator replay: error: no CAN interface")
    # a bus that cannot be opened: one line, a runtime error
    res = _cli("replay", str(log), "-i", "socketcan", "-c", "nosuchif0", env=env)
    assert res.returncode == EXIT_RUNTIME and "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bms-estimator replay: error: cannot open CAN bus socketcan:nosuchif0: ")


def test_exit_codes_tell_usage_data_and_runtime_apart(tmp_path, capsys):
    # usage: a bad option value
    with pytest.raises(SystemExit) as exc:
        main(["replay", "x.log", "--no-such-option"])
    assert exc.value.code == EXIT_USAGE
    # data: an input file that is missing or malformed
    assert main(["replay", str(tmp_path / "missing.log"), "-i", "virtual"]) == EXIT_DATA
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,current_a\n0,1\n")
    assert main(["fit", str(bad), "--ocv", str(bad), "--capacity-ah", "3"]) == EXIT_DATA
    # a good recording with a malformed OCV table: the table is the data at fault
    from bms_estimator.samples import drive_cycle

    table = tmp_path / "ocv.csv"
    table.write_text("soc,ocv_v\n0,abc\n1,4.1\n")
    assert main(["soc", str(drive_cycle("lg-hg2", "la92")), "--ocv", str(table), "--capacity-ah", "3"]) == EXIT_DATA
    assert "ocv.csv: line 2: non-numeric value 'abc' in column 'ocv_v'" in capsys.readouterr().err
    # usage: a configuration that is wrong
    cfg = tmp_path / "c.toml"
    cfg.write_text("[mqtt]\nport = 0\n")
    assert main(["run", "--config", str(cfg), "--check-config"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "mqtt.port" in err and "Traceback" not in err


def test_out_of_memory_is_one_line_and_a_runtime_error(monkeypatch, capsys):
    """numpy's MemoryError (an input too large for the machine) went out as a traceback."""
    import bms_estimator.cli.fit as fit

    def too_large(args):
        raise MemoryError("Unable to allocate 2.24 GiB for an array with shape (300004016,) and data type float64")

    monkeypatch.setattr(fit, "run", too_large)
    assert main(["fit", "x.csv", "--ocv", "x.csv", "--capacity-ah", "3"]) == EXIT_RUNTIME
    err = capsys.readouterr().err
    assert err == ("bms-estimator fit: error: out of memory: Unable to allocate 2.24 GiB for an array with shape "
                   "(300004016,) and data type float64\n")


def test_dashboard_that_never_connected_fails(tmp_path, capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here
    rc = main(["dashboard", "--broker", f"127.0.0.1:{port}", "--duration-s", "1"])
    assert rc == EXIT_RUNTIME
    err = capsys.readouterr().err
    # which broker and why (it read 'never connected to the broker: stopped')
    assert f"never connected to the broker at 127.0.0.1:{port} (" in err and "refused" in err, err


def test_dashboard_names_a_ca_file_that_is_missing_or_no_certificate(tmp_path, capsys):
    """Before: 'error: [Errno 2] No such file or directory' and a raw SSLError, neither naming --ca-file."""
    missing = tmp_path / "missing.pem"
    assert main(["dashboard", "--tls", "--ca-file", str(missing), "--duration-s", "1"]) == EXIT_DATA
    assert capsys.readouterr().err == f"bms-estimator dashboard: error: --ca-file {missing}: no such file or directory\n"
    not_pem = tmp_path / "good.csv"
    not_pem.write_text("time_s,current_a,voltage_v\n0,1,3.7\n")
    assert main(["dashboard", "--tls", "--ca-file", str(not_pem), "--duration-s", "1"]) == EXIT_DATA
    err = capsys.readouterr().err
    assert err.startswith(f"bms-estimator dashboard: error: --ca-file {not_pem}: not a CA certificate in PEM format")
    assert "SSLError" not in err and len(err.splitlines()) == 1, err


@pytest.mark.parametrize("option, value, why", [
    ("--pack", "a/#", "is not a pack id"), ("--pack", "+", "is not a pack id"), ("--pack", "a/b", "is not a pack id"),
    ("--base-topic", "#", "must not contain MQTT wildcards"), ("--base-topic", "site/+", "must not contain MQTT"),
    ("--base-topic", "bms/", "must not start or end with '/'"),
])
def test_dashboard_refuses_topic_parts_that_are_no_topic_level_before_it_starts(capsys, option, value, why):
    """'Invalid subscription filter.' came only after the live view had started, naming no option; the service's
    pack.pack_id and mqtt.base_topic refuse the same values."""
    with pytest.raises(SystemExit) as exc:
        main(["dashboard", option, value, "--broker", "127.0.0.1:1", "--duration-s", "1"])
    assert exc.value.code == EXIT_USAGE
    err = capsys.readouterr().err
    assert f"argument {option}: {value!r} {why}" in err, err


def test_unit_does_not_restart_on_configuration_or_data_errors():
    unit = (REPO / "deploy" / "bms-estimator.service").read_text()
    assert f"RestartPreventExitStatus={EXIT_USAGE} {EXIT_DATA}" in unit


def test_check_config_names_an_interface_that_is_not_there(tmp_path, capsys):
    """--check-config says 'configuration ok' only for a configuration that can receive: an unknown
    python-can interface is a usage error naming the known ones, an absent socketcan channel is said."""
    cfg = tmp_path / "c.toml"
    cfg.write_text('[can]\ninterface = "nosuchif"\n')
    assert main(["run", "--config", str(cfg), "--check-config"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "can.interface" in err and "unknown CAN interface 'nosuchif'" in err and "socketcan" in err
    assert "configuration ok" not in err
    cfg.write_text('[can]\ninterface = "socketcan"\nchannel = "nosuchif"\n')
    assert main(["run", "--config", str(cfg), "--check-config"]) == 0
    err = capsys.readouterr().err
    assert "no network interface 'nosuchif' here" in err and "configuration ok" not in err
    cfg.write_text('[can]\ninterface = "virtual"\nchannel = "x"\n')
    assert main(["run", "--config", str(cfg), "--check-config"]) == 0
    assert "configuration ok" in capsys.readouterr().err


def test_warnings_are_one_line_and_a_missing_file_is_named_plainly(tmp_path):
    """A repaired OCV table's warning came with the quoted source line of the library; a missing file read
    "[Errno 2] No such file or directory: 'x'". Both are one line for the user now."""
    from bms_estimator.samples import drive_cycle, ocv_table

    rows = (Path(ocv_table("lg-hg2")).read_text()).splitlines()
    a, b = rows[101].split(","), rows[102].split(",")
    a[1], b[1] = b[1], a[1]  # a 4.7 mV dip: repaired, with a warning
    rows[101], rows[102] = ",".join(a), ",".join(b)
    dip = tmp_path / "dip.csv"
    dip.write_text("\n".join(rows) + "\n")
    res = _cli("fit", str(drive_cycle("lg-hg2", "la92")), "--ocv", str(dip), "--capacity-ah", "3")
    assert res.returncode == 0, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bms-estimator fit: warning: ") and "dip.csv: ocv_v is not" in lines[0]
    res = _cli("soc", str(tmp_path / "missing.csv"), "--ocv", str(dip), "--capacity-ah", "3")
    assert res.returncode == EXIT_DATA
    assert res.stderr.strip() == f"bms-estimator soc: error: {tmp_path / 'missing.csv'}: No such file or directory"


def test_a_dbc_without_the_needed_messages_names_each_once_and_the_way_out(tmp_path, capsys):
    """A DBC without the mapping's messages listed 'PackMeasurement' three times (once per signal), and the
    missing output messages as a bare 'can.dbc: CellStateA'."""
    dbc = tmp_path / "other.dbc"
    dbc.write_text('VERSION ""\n\nBS_:\n\nBU_: ECU\n\nBO_ 256 Other: 8 ECU\n'
                   ' SG_ Speed : 0|16@1+ (0.1,0) [0|6553.5] "km/h" ECU\n')
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[can]\ninterface = "virtual"\nchannel = "x"\ndbc = "{dbc}"\n')
    assert main(["run", "--config", str(cfg), "--check-config"]) == EXIT_USAGE
    err = capsys.readouterr().err
    for name in ("PackMeasurement", "CellVoltages", "CellTemperatures"):
        assert err.count(f"can.mapping: message '{name}' not in the DBC") == 1, err
    assert ("can.dbc: message 'CellStateA' not in the DBC: can.output.enabled sends the project DBC's output "
            "messages; set [can.output] enabled = false") in err


def test_a_command_imports_only_what_it_needs():
    """``bms-estimator run`` (the daemon's start) and ``soc`` build only their own parser: neither pays for
    ``batch``'s Dask, and ``soc`` not for python-can; ``--help`` still lists every command."""
    probe = ("import sys; from bms_estimator.cli.__main__ import main\n"
             "try:\n    main([{args}])\nexcept SystemExit:\n    pass\n"
             "print(sorted(m for m in ('can', 'dask', 'distributed') if m in sys.modules))")
    for args, absent in (("'soc', '--help'", ["can", "dask", "distributed"]), ("'run', '--help'", ["dask", "distributed"])):
        res = subprocess.run([sys.executable, "-c", probe.format(args=args)], capture_output=True, text=True,
                             timeout=120, cwd=REPO)
        assert res.returncode == 0, res.stderr
        loaded = eval(res.stdout.strip().splitlines()[-1])
        assert not set(loaded) & set(absent), (args, loaded)
    listing = _cli("--help")
    assert listing.returncode == 0 and all(c in listing.stdout for c in ("soc", "batch", "sop-backtest", "run"))


def test_a_reader_that_closes_standard_output_ends_the_command_quietly():
    """'diagnose ... --json - | head -1' printed 'error: BrokenPipeError: [Errno 32] Broken pipe', exit 1, once its
    reader had what it wanted; a closed pipe is no error of the command's: no message, exit 141 (128 + SIGPIPE)."""
    from bms_estimator.samples import drive_cycle, ocv_table

    proc = subprocess.Popen([sys.executable, "-m", "bms_estimator.cli", "diagnose",
                             str(drive_cycle("panasonic-18650pf", "cycle_1")), "--ocv", str(ocv_table("panasonic-18650pf")),
                             "--capacity-ah", "2.9", "--no-lif", "--no-pairs", "--causes", "capacity_error",
                             "--json", "-"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            cwd=REPO)
    proc.stdout.close()  # the reader is gone before the command writes
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=300) == 141, err
    assert err == "", err
