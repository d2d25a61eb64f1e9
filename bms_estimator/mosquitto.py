"""A Mosquitto broker of our own on a free 127.0.0.1 port: the one launcher of the project
(the demo, the benchmarks and the tests start their brokers with it).

    with Mosquitto(workdir) as broker:          # or broker.start() ... broker.stop()
        connect("127.0.0.1", broker.port)

The config is generated in ``workdir`` (``listener <port> 127.0.0.1``, anonymous unless told
otherwise, no persistence unless asked, a deep per-client queue, log to ``mosquitto.log``,
plus ``extra_conf``); the process is stopped with SIGTERM, then SIGKILL.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

__all__ = ["Mosquitto", "MosquittoError", "find_mosquitto", "free_port"]

_PLACES = ("/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto", "/opt/homebrew/sbin/mosquitto")


class MosquittoError(RuntimeError):
    """The broker could not be started."""


def find_mosquitto() -> str | None:
    """Path of the ``mosquitto`` program, or None (``$MOSQUITTO`` first, then ``$PATH``, then sbin)."""
    candidates = [os.environ.get("MOSQUITTO"), shutil.which("mosquitto"), *_PLACES]
    for c in candidates:
        if c and Path(c).is_file() and os.access(c, os.X_OK):
            return c
    return None


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Mosquitto:
    """A Mosquitto process with a generated config file; can be stopped and started again on its port."""

    host = "127.0.0.1"

    def __init__(
        self,
        workdir: Path | str,
        port: int | None = None,
        extra_conf: str = "",
        *,
        anonymous: bool = True,
        persistence: bool = False,
        program: str | None = None,
    ) -> None:
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.port = port or free_port()
        self.extra_conf = extra_conf
        self.anonymous = anonymous
        self.persistence = persistence
        self.program = program or find_mosquitto()
        self.conf = self.workdir / "mosquitto.conf"
        self.logfile = self.workdir / "mosquitto.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def _write_conf(self) -> None:
        lines = [
            f"listener {self.port} 127.0.0.1",
            f"allow_anonymous {'true' if self.anonymous else 'false'}",
            f"persistence {'true' if self.persistence else 'false'}",
            # a subscriber that falls behind a replay at full speed must not lose the final states
            "max_queued_messages 1000000",
            f"log_dest file {self.logfile}",
            "log_type error",
            "log_type warning",
            "log_type notice",
            "log_type information",
        ]
        if self.persistence:
            lines.append(f"persistence_location {self.workdir}/")
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            lines.append("user root")  # do not drop to 'mosquitto' (it could not read the work folder)
        self.conf.write_text("\n".join(lines) + "\n" + self.extra_conf + "\n")

    def start(self, timeout: float = 10.0) -> Mosquitto:
        if self.program is None:
            raise MosquittoError("mosquitto is not installed (apt-get install mosquitto, or set $MOSQUITTO)")
        assert self.proc is None or self.proc.poll() is not None, "already running"
        self._write_conf()
        self.proc = subprocess.Popen([self.program, "-c", str(self.conf)], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, start_new_session=True)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                err = self.proc.stderr.read().decode(errors="replace") if self.proc.stderr else ""
                raise MosquittoError(f"mosquitto exited with {self.proc.returncode}: {err.strip()}\n{self.log_text()}")
            try:
                with socket.create_connection((self.host, self.port), timeout=0.2):
                    return self
            except OSError:
                time.sleep(0.02)
        self.stop()
        raise MosquittoError(f"mosquitto did not accept connections on port {self.port} within {timeout} s")

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5)
        if proc.stderr:
            with contextlib.suppress(Exception):
                proc.stderr.close()

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def log_text(self) -> str:
        return self.logfile.read_text(errors="replace") if self.logfile.exists() else ""

    def __enter__(self) -> Mosquitto:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
