"""Configuration: TOML + BMS_ environment, strict keys, clear errors, secrets."""

from __future__ import annotations

import io
import json
import re
import tomllib
from pathlib import Path

import pytest
from pydantic import BaseModel

from bms_estimator.service.config import ConfigError, ServiceConfig, load_config
from bms_estimator.service.logging import configure_logging, get_logger

REPO_ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = REPO_ROOT / "deploy" / "config.example.toml"


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch):
    import os

    for key in list(os.environ):
        if key.upper().startswith("BMS_") or key == "STATE_DIRECTORY":
            monkeypatch.delenv(key)


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "config.toml"
    p.write_text(text)
    return p


def test_defaults_without_file():
    cfg = load_config(None)
    assert cfg.mqtt.port == 1883 and cfg.mqtt.qos == 0 and cfg.mqtt.base_topic == "bms"
    assert cfg.health.host == "127.0.0.1"
    assert cfg.estimator.sample_period_s == 1.0
    assert cfg.state.path == Path("/var/lib/bms-estimator/state.npz")
    assert cfg.logging.format == "auto"


def test_state_path_follows_systemd_state_directory(monkeypatch, tmp_path):
    monkeypatch.setenv("STATE_DIRECTORY", f"{tmp_path}/a:{tmp_path}/b")
    assert load_config(None).state.path == tmp_path / "a" / "state.npz"


def test_toml_and_env_override(tmp_path, monkeypatch):
    path = write(
        tmp_path,
        """
[pack]
pack_id = "truck7"
n_cells = 96
capacity_ah = 280
[can]
channel = "can1"
mapping = { current = { message = "PackI", signal = "I" } }
[can.bus]
reopen_max_s = 10.0
[estimator.core]
window = 30
[mqtt]
host = "file-host"
port = 1884
username = "bms"
password = "from-file"
[mqtt.tls]
enabled = false
""",
    )
    monkeypatch.setenv("BMS_MQTT__HOST", "env-host")
    monkeypatch.setenv("BMS_MQTT__TLS__ENABLED", "true")
    monkeypatch.setenv("bms_mqtt__qos", "2")  # case-insensitive
    monkeypatch.setenv("BMS_CAN__BITRATE", "250000")
    cfg = load_config(path)
    assert cfg.pack.pack_id == "truck7" and cfg.pack.n_cells == 96 and cfg.pack.capacity_ah == 280.0
    assert cfg.mqtt.host == "env-host"  # env wins
    assert cfg.mqtt.port == 1884  # file value kept (deep merge)
    assert cfg.mqtt.username == "bms"
    assert cfg.mqtt.tls.enabled is True
    assert cfg.mqtt.qos == 2
    assert cfg.can.channel == "can1"
    assert cfg.can.mapping == {"current": {"message": "PackI", "signal": "I"}}
    assert cfg.can.bus_kwargs() == {
        "interface": "socketcan", "channel": "can1", "fd": False, "bitrate": 250000, "reopen_max_s": 10.0,
    }
    assert cfg.estimator.soc_config.identifier.window == 30


@pytest.mark.parametrize(
    ("toml", "env", "expected"),
    [
        ("[mqtt]\nhostt = 'x'\n", {}, "mqtt.hostt: Extra inputs are not permitted (did you mean 'host'?)"),
        ("[mqtt.tls]\nca = 'x'\n", {}, "mqtt.tls.ca: Extra inputs are not permitted"),
        ("[nonsense]\na = 1\n", {}, "nonsense: Extra inputs are not permitted"),
        ("[health]\nhost = '127.0.0.1'\nprot = 1\n", {}, "health.prot: Extra inputs are not permitted (did you mean 'port'?)"),
        ("", {"BMS_MQTT__PROT": "1"}, "mqtt.prot: Extra inputs are not permitted (did you mean 'port'?)"),
        ("[estimator.core]\nwindw = 20\n", {}, "estimator.core.windw: Extra inputs are not permitted (did you mean "
                                                  "'window'?)"),
        ("[can.output]\nperiod = 1\n", {}, "can.output.period: Extra inputs are not permitted (did you mean 'period_s'?)"),
        ("", {"BMS_MQTTT__PORT": "1"},
         "BMS_MQTTT__PORT (environment): unknown setting; sections are can, estimator, health, "
         "logging, mqtt, pack, state"),
    ],
)
def test_unknown_keys_are_rejected_by_name(tmp_path, monkeypatch, toml, env, expected):
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    with pytest.raises(ConfigError) as exc:
        load_config(write(tmp_path, toml))
    assert expected in exc.value.problems
    assert expected in str(exc.value)


def test_bad_values_name_each_field_one_line_each(tmp_path):
    path = write(
        tmp_path,
        """
[pack]
pack_id = "a/b"
n_cells = 0
[mqtt]
port = "many"
qos = 3
reconnect_min_s = 5.0
reconnect_max_s = 1.0
[health]
host = "0.0.0.0"
[logging]
format = "xml"
""",
    )
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    problems = exc.value.problems
    fields = [p.split(":", 1)[0] for p in problems]
    assert fields == [
        "pack.pack_id",
        "pack.n_cells",
        "mqtt.port",
        "mqtt.qos",
        "mqtt.reconnect_max_s",
        "health.host",
        "logging.format",
    ]
    text = str(exc.value)
    assert text.splitlines()[0].startswith("invalid configuration (")
    assert len(text.splitlines()) == 1 + len(problems)
    assert any(p.startswith("mqtt.port: Input should be a valid integer") for p in problems)
    assert any("loopback" in p for p in problems)


def test_env_value_type_error_names_field(monkeypatch):
    monkeypatch.setenv("BMS_MQTT__PORT", "70000")
    with pytest.raises(ConfigError) as exc:
        load_config(None)
    assert exc.value.problems == ["mqtt.port: Input should be less than or equal to 65535 (got '70000')"]


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_non_finite_numbers_are_called_what_they_are(tmp_path, value):
    """A NaN capacity was reported as 'less than or equal to 100000' (issue 16)."""
    path = write(tmp_path, f"[pack]\ncapacity_ah = {value}\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert [p.split(" (got")[0] for p in exc.value.problems] == ["pack.capacity_ah: Input should be a finite number"]


def test_remote_health_needs_opt_in(monkeypatch):
    monkeypatch.setenv("BMS_HEALTH__HOST", "0.0.0.0")
    with pytest.raises(ConfigError):
        load_config(None)
    monkeypatch.setenv("BMS_HEALTH__ALLOW_REMOTE", "true")
    assert load_config(None).health.host == "0.0.0.0"


def test_toml_syntax_error_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="invalid TOML") as exc:
        load_config(write(tmp_path, "[mqtt\nport = 1\n"))
    assert "line 1" in str(exc.value)
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.toml")


def test_a_config_that_is_not_utf8_names_the_file(tmp_path):
    """It read "'utf-8' codec can't decode byte 0xff in position 0" without the file, as a bare ValueError."""
    path = tmp_path / "latin1.toml"
    path.write_bytes('[pack]\npack_id = "k\xfchl"\n'.encode("latin-1"))
    with pytest.raises(ConfigError, match="invalid TOML in .*latin1.toml") as exc:
        load_config(path)
    assert "not UTF-8 text: invalid start byte at byte 19" in str(exc.value)


def test_secrets_never_in_redacted_dump_repr_or_logs(tmp_path, monkeypatch):
    secret = "pa55-Very-Secret"
    path = write(tmp_path, f"[mqtt]\nusername = 'bms'\npassword = '{secret}'\n")
    cfg = load_config(path)
    assert cfg.mqtt.password is not None and cfg.mqtt.password.get_secret_value() == secret
    dump = cfg.redacted()
    assert dump["mqtt"]["password"] == "**********"
    assert secret not in json.dumps(dump)
    assert secret not in repr(cfg) and secret not in str(cfg)

    for fmt in ("json", "console"):
        buf = io.StringIO()
        configure_logging("DEBUG", fmt, stream=buf, env={})
        log = get_logger("test")
        log.info("config loaded", config=cfg.redacted())
        log.info("config object", cfg=cfg, mqtt=cfg.mqtt)
        try:
            raise RuntimeError("boom")
        except RuntimeError:
            log.exception("with traceback")  # locals of this frame hold the secret
        out = buf.getvalue()
        assert "config loaded" in out and "**********" in out
        assert secret not in out, fmt

    # A bad password value is reported without echoing it.
    path2 = write(tmp_path, "[mqtt]\nusername = 'u'\npassword = 12345678\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path2)
    assert "12345678" not in str(exc.value) and exc.value.problems[0].startswith("mqtt.password:")


def _leaf_keys(model: type[BaseModel], prefix: str = "") -> list[tuple[str, str]]:
    out = []
    for name, field in model.model_fields.items():
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            out += _leaf_keys(ann, f"{prefix}{name}.")
        else:
            out.append((prefix.rstrip("."), name))
    return out


def test_example_config_validates_and_documents_every_key(monkeypatch):
    cfg = load_config(EXAMPLE)
    assert isinstance(cfg, ServiceConfig)
    assert cfg.model_dump() == ServiceConfig().model_dump()  # the example shows the defaults

    text = EXAMPLE.read_text()
    sections: dict[str, str] = {}
    current = ""
    for line in text.splitlines():
        m = re.match(r"^\[([a-z_.]+)\]\s*$", line)
        if m:
            current = m.group(1)
            continue
        sections[current] = sections.get(current, "") + line + "\n"
    missing = []
    for section, key in _leaf_keys(ServiceConfig):
        body = sections.get(section, "")
        if (section, key) in {("estimator", "core"), ("can", "bus")} and f"{section}.{key}" in sections:
            continue
        if section == "estimator.core.identifier" or (section, key) == ("estimator.core", "identifier"):
            continue  # documented flat, under [estimator.core]
        if not re.search(rf"^#?\s*{re.escape(key)}\s*=", body, re.M):
            missing.append(f"{section}.{key}")
    assert missing == []
    # the core's section is made from the core's dataclasses, so it cannot go stale
    from bms_estimator.service.config import core_example_toml

    assert core_example_toml() in text
    # and it is plain TOML
    tomllib.loads(text)



def test_the_data_location_variable_is_not_a_config_error(tmp_path, monkeypatch):
    """BMS_SHARED_DATA belongs to the offline tools; a service in the same environment still starts."""
    from bms_estimator.service.config import load_config

    monkeypatch.setenv("BMS_SHARED_DATA", str(tmp_path))
    monkeypatch.setenv("BMS_PACK__N_CELLS", "4")
    assert load_config(None).pack.n_cells == 4
    monkeypatch.setenv("BMS_SHARDE_DATA", "typo")  # any other unknown BMS_ variable is still an error
    with pytest.raises(Exception, match="BMS_SHARDE_DATA"):
        load_config(None)


def test_core_parameter_named_once_with_the_cores_bound(tmp_path, monkeypatch):
    """estimator.core is validated once, against the core's own dataclass bounds (the
    RLS needs forgetting in [0.9, 1]: the daemon once accepted (0, 1])."""
    from bms_estimator.core.identifier import IdentifierConfig

    path = tmp_path / "c.toml"
    path.write_text("[estimator.core]\nforgetting = 0.5\n[estimator.core.identifier]\ntau_min_s = -1\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    problems = exc.value.problems
    assert problems == [
        "estimator.core.identifier.tau_min_s: Input should be greater than 0 (got -1)",
        "estimator.core.forgetting: Input should be greater than or equal to 0.9 (got 0.5)",
    ] or sorted(problems) == sorted([
        "estimator.core.identifier.tau_min_s: Input should be greater than 0 (got -1)",
        "estimator.core.forgetting: Input should be greater than or equal to 0.9 (got 0.5)",
    ])
    # the bound is the core's: the dataclass carries it
    import typing

    meta = typing.get_type_hints(IdentifierConfig, include_extras=True)["forgetting"].__metadata__
    assert any(getattr(m, "ge", None) == 0.9 for m in meta)
    # the environment goes through the same validation
    monkeypatch.setenv("BMS_ESTIMATOR__CORE__WINDOW", "0")
    with pytest.raises(ConfigError) as exc:
        load_config(None)
    assert exc.value.problems == ["estimator.core.window: Input should be greater than or equal to 1 (got '0')"]
    monkeypatch.setenv("BMS_ESTIMATOR__CORE__WINDOW", "25")
    monkeypatch.setenv("BMS_ESTIMATOR__CORE__CAPACITY_SOC_UPDATE", "line")
    soc = load_config(None).estimator.soc_config
    assert soc.identifier.window == 25 and soc.capacity_soc_update == "line"
    # a rule across fields is the core's too, named under estimator.core
    path.write_text("[estimator.core]\ntau_min_s = 600.0\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert exc.value.problems == ["estimator.core: tau_min_s must be below tau_max_s, got 600.0 and 500.0"]


def test_an_environment_value_that_is_not_json_names_the_variable_not_the_file(tmp_path, monkeypatch):
    """It read 'invalid configuration (ok.toml): error parsing value for field "estimator" from source
    "EnvSettingsSource"': the file blamed, the variable not named."""
    path = tmp_path / "ok.toml"
    path.write_text("[pack]\nn_cells = 4\n")
    monkeypatch.setenv("BMS_ESTIMATOR__CORE__WINDOW", "25")  # a fine variable of the same section is not blamed
    monkeypatch.setenv("BMS_ESTIMATOR__CORE__CAPACITY_BOUNDS", "[1,2")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert exc.value.header == "invalid configuration (environment):"
    assert exc.value.problems == ["BMS_ESTIMATOR__CORE__CAPACITY_BOUNDS (environment): not valid JSON "
                                  "(Expecting ',' delimiter: line 1 column 5 (char 4))"]
    assert "ok.toml" not in str(exc.value)
    monkeypatch.setenv("BMS_ESTIMATOR__CORE__CAPACITY_BOUNDS", "[0.8, 1.1]")
    assert load_config(path).pack.n_cells == 4


def test_secrets_come_from_systemd_credentials(tmp_path, monkeypatch):
    """LoadCredential= puts a file per secret in $CREDENTIALS_DIRECTORY, named like the setting
    (mqtt__password); it wins over the file, the environment wins over it; other credentials
    are not ours and are ignored."""
    creds = tmp_path / "creds"
    creds.mkdir()
    (creds / "mqtt__password").write_text("from-credential\n")
    (creds / "something_else").write_text("x")
    path = tmp_path / "c.toml"
    path.write_text('[mqtt]\nusername = "bms"\npassword = "from-file"\nport = 1884\n')
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(creds))
    cfg = load_config(path)
    assert cfg.mqtt.password.get_secret_value() == "from-credential" and cfg.mqtt.port == 1884
    assert "from-credential" not in str(cfg.redacted())
    monkeypatch.setenv("BMS_MQTT__PASSWORD", "from-env")
    assert load_config(path).mqtt.password.get_secret_value() == "from-env"
    monkeypatch.delenv("BMS_MQTT__PASSWORD")
    (creds / "mqtt__no_such_key").write_text("1")  # a credential for a setting that does not exist
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert any(p.startswith("mqtt.no_such_key:") for p in exc.value.problems)
