"""structlog setup: JSON under systemd / on request, console in a terminal."""

from __future__ import annotations

import io
import json
import logging
import os

import pytest

from bms_estimator.service.logging import configure_logging, detect_format, get_logger


@pytest.fixture(autouse=True)
def _restore_root_logging():
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


@pytest.mark.parametrize(
    ("fmt", "env", "expected"),
    [
        ("auto", {"JOURNAL_STREAM": "8:12345"}, "json"),
        ("auto", {"INVOCATION_ID": "abc"}, "json"),
        ("auto", {}, "console"),
        ("json", {}, "json"),
        ("console", {"INVOCATION_ID": "abc"}, "console"),
    ],
)
def test_detect_format(fmt, env, expected):
    assert detect_format(fmt, env) == expected


def test_json_lines_under_systemd_including_stdlib_loggers():
    buf = io.StringIO()
    assert configure_logging("INFO", "auto", stream=buf, env={"INVOCATION_ID": "x"}) == "json"
    log = get_logger("bms.test", pack_id="p1")
    log.info("tick", soc=0.5, n=3)
    log.debug("hidden")  # below INFO
    logging.getLogger("mqtt").warning("paho says %s", "hi")  # a library's stdlib logger
    try:
        1 / 0
    except ZeroDivisionError:
        log.exception("failed")
    lines = buf.getvalue().splitlines()
    assert len(lines) == 3
    records = [json.loads(line) for line in lines]  # every line is one JSON object
    tick, lib, err = records
    assert tick["event"] == "tick" and tick["soc"] == 0.5 and tick["n"] == 3 and tick["pack_id"] == "p1"
    assert tick["level"] == "info" and tick["logger"] == "bms.test" and tick["timestamp"].endswith("Z")
    assert lib["event"] == "paho says hi" and lib["level"] == "warning" and lib["logger"] == "mqtt"
    assert err["level"] == "error" and err["exception"][0]["exc_type"] == "ZeroDivisionError"
    assert "locals" not in err["exception"][0]["frames"][0]


def test_console_in_a_terminal_is_readable_not_json():
    buf = io.StringIO()
    assert configure_logging("debug", "auto", stream=buf, env={}) == "console"
    get_logger("bms.test").debug("hello world", cell=3)
    out = buf.getvalue()
    assert "hello world" in out and "cell=3" in out and "debug" in out
    with pytest.raises(json.JSONDecodeError):
        json.loads(out.splitlines()[0])
    assert "\x1b[" not in out  # no colour codes when the stream is not a TTY


def test_reconfigure_replaces_handler_and_level():
    b1, b2 = io.StringIO(), io.StringIO()
    configure_logging("INFO", "json", stream=b1, env={})
    configure_logging("WARNING", "json", stream=b2, env={})
    log = get_logger("bms.test")
    log.info("dropped")
    log.warning("kept")
    assert b1.getvalue() == ""
    assert [json.loads(x)["event"] for x in b2.getvalue().splitlines()] == ["kept"]


def test_journal_priority_prefix_only_when_stream_is_the_journal(tmp_path):
    path = tmp_path / "journal"
    with path.open("w") as stream:
        st = os.fstat(stream.fileno())
        configure_logging("INFO", "auto", stream=stream, env={"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})
        get_logger("bms.test").warning("w")
        get_logger("bms.test").info("i")
    lines = path.read_text().splitlines()
    assert lines[0].startswith("<4>{") and lines[1].startswith("<6>{")
    assert json.loads(lines[0][3:])["event"] == "w"
