"""The deploy guide's commands, run as written: file modes, and what an unprivileged user can read.

The unit runs as a DynamicUser: a config file the guide installs root-only (it once said 0640)
stops the first start with "cannot read config file: Permission denied". Here the guide's
``install`` lines run under a scratch root, the service's config is read as ``nobody``, and
the password file is not readable by ``nobody`` but reaches the service as a credential.
"""

from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
import tempfile
from pathlib import Path

import pytest

from bms_estimator.service.config import load_config

REPO = Path(__file__).resolve().parents[2]
GUIDE = REPO / "deploy" / "README.md"
NOBODY = 65534


def _sh_blocks() -> list[str]:
    return re.findall(r"```sh\n(.*?)```", GUIDE.read_text(), re.S)


def _install_lines(block: str) -> list[str]:
    return [line.split("#", 1)[0].strip() for line in block.splitlines()
            if re.match(r"^(install|printf) ", line.strip()) and "/etc/bms-estimator" in line]


def _as_written(line: str, root: Path) -> str:
    return line.replace("/etc/", f"{root}/etc/").replace(" deploy/", f" {REPO}/deploy/")


def _as_nobody(*cmd: str) -> subprocess.CompletedProcess:
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("setpriv (util-linux) not installed: cannot act as an unprivileged user")
    return subprocess.run([setpriv, f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", *cmd],
                          capture_output=True, text=True, timeout=30)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0,
                    reason="the guide's commands install as root; run the suite as root to check them")
def test_install_commands_as_written_give_a_config_the_service_user_can_read(monkeypatch):
    blocks = _sh_blocks()
    config_cmds = _install_lines(blocks[0])
    secret_cmds = _install_lines(next(b for b in blocks if "LoadCredential" in b))
    assert any("config.toml" in c for c in config_cmds) and any("mqtt_password" in c for c in secret_cmds)
    root = Path(tempfile.mkdtemp(prefix="bms-deploy-", dir="/tmp"))
    try:
        root.chmod(0o755)  # like / : traversable by everyone
        for cmd in config_cmds + secret_cmds:
            subprocess.run(["bash", "-euo", "pipefail", "-c", _as_written(cmd, root)], check=True, timeout=30)
        etc = root / "etc" / "bms-estimator"
        config = etc / "config.toml"
        secret = etc / "mqtt_password"
        assert stat.S_IMODE(etc.stat().st_mode) == 0o755
        assert stat.S_IMODE(config.stat().st_mode) == 0o644
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600
        # the service's dynamic user can read the config, and nothing else can read the secret
        res = _as_nobody("cat", str(config))
        assert res.returncode == 0, res.stderr
        assert res.stdout == config.read_text()
        res = _as_nobody("cat", str(secret))
        assert res.returncode != 0 and "Permission denied" in res.stderr
        # the installed example is a valid configuration; the credential (as systemd would hand
        # it over, in $CREDENTIALS_DIRECTORY) supplies the password
        creds = root / "credentials"
        creds.mkdir()
        shutil.copy(secret, creds / "mqtt__password")
        monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(creds))
        config.write_text(config.read_text().replace('# username = "bms"', 'username = "bms"'))
        cfg = load_config(config)
        assert cfg.mqtt.password is not None and cfg.mqtt.password.get_secret_value() == "the-password"
        assert "the-password" not in str(cfg.redacted())
    finally:
        shutil.rmtree(root, ignore_errors=True)


def test_the_unit_loads_the_password_as_a_credential_not_from_the_environment():
    guide = GUIDE.read_text()
    unit = (REPO / "deploy" / "bms-estimator.service").read_text()
    assert "EnvironmentFile" not in guide and "EnvironmentFile" not in unit
    assert "LoadCredential=mqtt__password:" in guide and "0640" not in guide
