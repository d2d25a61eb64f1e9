"""What ``bms-estimator run`` refuses before it starts (exit 2, one line per problem naming the key and
the path), where the service would otherwise run on a configuration that can never work."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from bms_estimator.cli.__main__ import main as cli_main


def write_config(tmp_path: Path, extra: str = "", *, state: Path | None = None) -> Path:
    state = state if state is not None else tmp_path / "state" / "state.npz"
    path = tmp_path / "bms.toml"
    path.write_text("[pack]\nn_cells = 4\n"
                    "[can]\ninterface = 'virtual'\nchannel = 'check-config'\n"
                    f"[state]\npath = '{state}'\n" + extra)
    return path


def check_config(path: Path, capsys) -> tuple[int, str]:
    code = cli_main(["run", "--config", str(path), "--check-config"])
    return code, capsys.readouterr().err


@pytest.mark.parametrize("key", ["ca_file", "cert_file"])
def test_a_tls_file_that_is_missing_or_not_pem_is_named_before_the_start(tmp_path, capsys, key):
    """It passed --check-config, and the running service logged 'mqtt client setup failed:
    FileNotFoundError: [Errno 2] No such file or directory' at every reconnect, naming neither
    the key nor the file."""
    missing = tmp_path / "tls" / "missing.pem"
    code, err = check_config(write_config(tmp_path, f"[mqtt.tls]\nenabled = true\n{key} = '{missing}'\n"), capsys)
    assert code == 2, err
    assert f"mqtt.tls.{key}: {missing}: no such file or directory" in err and "Errno" not in err, err

    garbage = tmp_path / "garbage.pem"
    garbage.write_text("not a certificate\n")
    code, err = check_config(write_config(tmp_path, f"[mqtt.tls]\nenabled = true\n{key} = '{garbage}'\n"), capsys)
    assert code == 2, err
    assert f"mqtt.tls.{key}: {garbage}:" in err and "Traceback" not in err, err


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command to make a test key")
@pytest.mark.parametrize("separate_key", [True, False])
def test_an_encrypted_tls_key_is_named_as_such_and_never_prompts(tmp_path, capsys, separate_key):
    """An encrypted client key made OpenSSL ask for its passphrase on the terminal (a daemon has none), and
    without one the error said 'not a PEM certificate and its key'. Now it is loaded with an empty
    passphrase and the error says the key is encrypted, naming the key and the file."""
    key, cert = tmp_path / "client.key", tmp_path / "client.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-keyout", str(key), "-out", str(cert),
                    "-days", "1", "-subj", "/CN=bms-test", "-passout", "pass:secret"],
                   check=True, capture_output=True, stdin=subprocess.DEVNULL)
    if separate_key:
        tls = f"cert_file = '{cert}'\nkey_file = '{key}'\n"
        named = f"mqtt.tls.key_file: {key}:"
    else:  # certificate and key in one file
        cert.write_text(cert.read_text() + key.read_text())
        tls = f"cert_file = '{cert}'\n"
        named = f"mqtt.tls.cert_file: {cert}:"
    code, err = check_config(write_config(tmp_path, f"[mqtt.tls]\nenabled = true\n{tls}"), capsys)
    assert code == 2, err
    assert named in err and "encrypted" in err and "Traceback" not in err, err


def test_tls_files_are_not_read_while_mqtt_is_off(tmp_path, capsys):
    extra = f"[mqtt]\nenabled = false\n[mqtt.tls]\nenabled = true\nca_file = '{tmp_path / 'missing.pem'}'\n"
    code, err = check_config(write_config(tmp_path, extra), capsys)
    assert code == 0, err


def test_a_state_path_that_is_a_directory_is_refused_and_left_alone(tmp_path, capsys):
    """``state.path = '/var/lib/bms-estimator'`` (the StateDirectory, not a file in it) passed
    --check-config; the running service then renamed the operator's directory, contents and all,
    to ``<dir>.corrupt-<time>`` ("not a regular file") and wrote its state file in its place."""
    folder = tmp_path / "var-lib"
    folder.mkdir()
    (folder / "notes.txt").write_text("keep")
    code, err = check_config(write_config(tmp_path, state=folder), capsys)
    assert code == 2, err
    assert f"state.path: {folder} is a directory" in err and str(folder / "state.npz") in err, err
    assert cli_main(["run", "--config", str(write_config(tmp_path, state=folder))]) == 2
    assert (folder / "notes.txt").read_text() == "keep"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("var-lib")] == ["var-lib"]


def test_a_state_path_through_a_file_is_refused(tmp_path, capsys):
    """A state file under a path that is a file: every save failed ('File exists'), found at the first one."""
    afile = tmp_path / "hostname"
    afile.write_text("x")
    code, err = check_config(write_config(tmp_path, state=afile / "state.npz"), capsys)
    assert code == 2, err
    assert f"state.path: {afile} is not a directory" in err, err
    code, err = check_config(write_config(tmp_path, state=tmp_path / "not" / "yet" / "state.npz"), capsys)
    assert code == 0, err  # a directory that does not exist yet is made by the first save


def test_an_mqtt_buffer_smaller_than_one_sample_is_refused(tmp_path, capsys):
    """Each sample queues its pack.n_cells + 1 topics at once, and a full buffer evicts the oldest:
    with ``mqtt.buffer_max`` below that, the first cells of every sample were evicted unsent, never
    published while the broker was up, counted only as ``bms_mqtt_dropped_total``."""
    code, err = check_config(write_config(tmp_path, "[mqtt]\nbuffer_max = 3\n"), capsys)
    assert code == 2, err
    assert "mqtt.buffer_max: 3 is less than the 5 topics of one sample (pack.n_cells 4 and the pack)" in err, err
    code, err = check_config(write_config(tmp_path, "[mqtt]\nbuffer_max = 5\n"), capsys)
    assert code == 0, err
    code, err = check_config(write_config(tmp_path, "[mqtt]\nenabled = false\nbuffer_max = 3\n"), capsys)
    assert code == 0, err
