"""Constants and a Mosquitto runner shared by the replay tests (imported by module name)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
from pathlib import Path

from service_helpers import free_port

MOSQUITTO = os.environ.get("MOSQUITTO", "/usr/sbin/mosquitto")

#: the shared encoded log: first 600 s of the shipped Panasonic cycle_1, 8 cells
CELL, CYCLE, N_CELLS, DURATION_S, SEED = "panasonic-18650pf", "cycle_1", 8, 600, 7

class Broker:
    def __init__(self, workdir: Path) -> None:
        self.workdir = workdir
        self.host, self.port = "127.0.0.1", free_port()
        self.proc: subprocess.Popen | None = None

    def start(self) -> "Broker":
        conf = self.workdir / "mosquitto.conf"
        lines = [f"listener {self.port} 127.0.0.1", "allow_anonymous true", "persistence false",
                 f"log_dest file {self.workdir / 'mosquitto.log'}"]
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            lines.append("user root")
        conf.write_text("\n".join(lines) + "\n")
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"mosquitto exited with {self.proc.returncode}")
            try:
                with socket.create_connection((self.host, self.port), timeout=0.2):
                    return self
            except OSError:
                time.sleep(0.02)
        self.stop()
        raise RuntimeError("mosquitto did not start")

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
        if proc.stderr:
            proc.stderr.close()
