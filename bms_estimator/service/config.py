"""Service configuration: a TOML file plus ``BMS_`` environment overrides.

Precedence (highest first): environment variables ``BMS_<SECTION>__<KEY>``
(nested with ``__``, case-insensitive, e.g. ``BMS_MQTT__HOST``,
``BMS_MQTT__TLS__ENABLED=true``), then the TOML file, then the defaults below.

Every model forbids unknown keys, so a typo anywhere (file or environment) is
an error that names the key. Validation problems are raised as
:class:`ConfigError` with one ``section.key: message`` line per problem.

Secrets (the MQTT password) are :class:`pydantic.SecretStr`; use
:meth:`ServiceConfig.redacted` for anything that goes to a log.
"""

from __future__ import annotations

import ipaddress
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    ValidationInfo,
    field_validator,
)
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

__all__ = [
    "CanConfig",
    "CanOutputConfig",
    "ConfigError",
    "EstimatorConfig",
    "HealthConfig",
    "LoggingConfig",
    "MqttConfig",
    "PackConfig",
    "ServiceConfig",
    "StateConfig",
    "TlsConfig",
    "load_config",
]

ENV_PREFIX = "BMS_"
REDACTED = "**********"

_TOPIC_FORBIDDEN = set("+#\x00")
_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"


class ConfigError(Exception):
    """Invalid or unreadable configuration.

    ``str(err)`` is a human-readable message: a header line then one line per
    problem (``mqtt.port: Input should be less than or equal to 65535``).
    ``err.problems`` holds the problem lines alone.
    """

    def __init__(self, header: str, problems: list[str] | None = None) -> None:
        self.header = header
        self.problems = list(problems or [])
        super().__init__("\n".join([header, *("  " + p for p in self.problems)]))


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_default=True)


# --------------------------------------------------------------------------- pack
class PackConfig(_Strict):
    pack_id: str = Field("pack0", pattern=_ID_PATTERN, description="used in MQTT topics and HA ids")
    n_cells: int = Field(16, ge=1, le=1024)
    capacity_ah: float = Field(50.0, gt=0, le=1e5)
    ocv_csv: Path | None = Field(None, description="OCV(SOC) table; None = built-in sample curve")


# ---------------------------------------------------------------------------- can
class CanOutputConfig(_Strict):
    enabled: bool = Field(True, description="publish the estimator state as frames of the project's DBC")
    period_s: float = Field(1.0, gt=0, le=3600)


class CanConfig(_Strict):
    # Field names follow bms_estimator.can.bus.BusConfig, which validates the bus part.
    interface: str = "socketcan"
    channel: str | int = "can0"
    bitrate: int | None = Field(None, gt=0, le=8_000_000, description="None = keep the interface's setting")
    data_bitrate: int | None = Field(None, gt=0, le=16_000_000, description="CAN FD data phase")
    fd: bool = False
    bus: dict[str, Any] = Field(default_factory=dict, description="further BusConfig options, checked by the CAN module")
    dbc: Path | None = Field(None, description="None = the project's DBC")
    # Input mapping: preset name ("default", "foxbms"), a TOML file path, or an
    # inline table; validated by bms_estimator.can.mapping.load_mapping.
    mapping: str | dict[str, Any] = "default"
    output: CanOutputConfig = Field(default_factory=CanOutputConfig)

    def bus_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``bms_estimator.can.bus.BusConfig``."""
        kw: dict[str, Any] = {"interface": self.interface, "channel": self.channel, "fd": self.fd}
        if self.bitrate is not None:
            kw["bitrate"] = self.bitrate
        if self.data_bitrate is not None:
            kw["data_bitrate"] = self.data_bitrate
        kw.update(self.bus)
        return kw


# ---------------------------------------------------------------------- estimator
class EstimatorConfig(_Strict):
    sample_period_s: float = Field(1.0, gt=0, le=60)
    staleness_s: float = Field(5.0, gt=0, le=3600)
    # Free-form parameters handed to the numerical core (lif window, noise, ...).
    core: dict[str, Any] = Field(default_factory=dict)


# --------------------------------------------------------------------------- mqtt
class TlsConfig(_Strict):
    enabled: bool = False
    ca_file: Path | None = Field(None, description="None = system trust store")
    cert_file: Path | None = None
    key_file: Path | None = None
    insecure: bool = Field(False, description="skip certificate and hostname verification (testing only)")

    @field_validator("key_file")
    @classmethod
    def _key_needs_cert(cls, v: Path | None, info: ValidationInfo) -> Path | None:
        if v is not None and info.data.get("cert_file") is None:
            raise ValueError("key_file given without cert_file")
        return v


def _check_topic_part(value: str, *, allow_empty: bool = False) -> str:
    if not value and not allow_empty:
        raise ValueError("must not be empty")
    if _TOPIC_FORBIDDEN & set(value):
        raise ValueError("must not contain MQTT wildcards '+', '#' or NUL")
    if value.startswith("/") or value.endswith("/") or "//" in value:
        raise ValueError("must not start or end with '/' or contain empty levels")
    return value


class MqttConfig(_Strict):
    enabled: bool = True
    host: str = Field("localhost", min_length=1)
    port: int = Field(1883, ge=1, le=65535)
    client_id: str | None = Field(None, description="None = bms-estimator-<pack_id>")
    username: str | None = None
    password: SecretStr | None = None
    tls: TlsConfig = Field(default_factory=TlsConfig)
    qos: int = Field(1, ge=0, le=2, description="0, 1 or 2 for every message")
    base_topic: str = "bms"
    discovery: bool = True
    discovery_prefix: str = "homeassistant"
    keepalive: int = Field(30, ge=5, le=65535)
    timeout_s: float = Field(10.0, gt=0, le=300, description="connect/ack timeout")
    reconnect_min_s: float = Field(1.0, gt=0, le=3600)
    reconnect_max_s: float = Field(60.0, gt=0, le=86400)
    buffer_max: int = Field(4096, ge=1, le=1_000_000)

    @field_validator("base_topic", "discovery_prefix")
    @classmethod
    def _topic(cls, v: str) -> str:
        return _check_topic_part(v)

    @field_validator("reconnect_max_s")
    @classmethod
    def _backoff_order(cls, v: float, info: ValidationInfo) -> float:
        lo = info.data.get("reconnect_min_s")
        if lo is not None and v < lo:
            raise ValueError(f"must be >= reconnect_min_s ({lo})")
        return v

    @field_validator("password")
    @classmethod
    def _password_needs_user(cls, v: SecretStr | None, info: ValidationInfo) -> SecretStr | None:
        if v is not None and info.data.get("username") is None:
            raise ValueError("password given without username")
        return v


# -------------------------------------------------------------------------- state
def _default_state_path() -> Path:
    # systemd's StateDirectory= exports STATE_DIRECTORY (colon-separated list).
    base = os.environ.get("STATE_DIRECTORY", "").split(":")[0] or "/var/lib/bms-estimator"
    return Path(base) / "state.npz"


class StateConfig(_Strict):
    path: Path = Field(default_factory=_default_state_path)
    save_interval_s: float = Field(60.0, gt=0, le=86400)
    max_age_s: float | None = Field(7 * 86400.0, gt=0, description="older saved state is ignored; None = no limit")


# ------------------------------------------------------------------------- health
def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class HealthConfig(_Strict):
    enabled: bool = True
    # Declared before ``host`` so the host validator can see it.
    allow_remote: bool = Field(False, description="must be true to bind a non-loopback host")
    host: str = "127.0.0.1"
    port: int = Field(9108, ge=0, le=65535, description="0 = any free port")
    stale_after_periods: float = Field(3.0, gt=0, description="/healthz is 503 after this many missed ticks")

    @field_validator("host")
    @classmethod
    def _loopback(cls, v: str, info: ValidationInfo) -> str:
        if not info.data.get("allow_remote", False) and not _is_loopback(v):
            raise ValueError(f"{v!r} is not a loopback address; set health.allow_remote = true to expose it")
        return v


# ------------------------------------------------------------------------ logging
class LoggingConfig(_Strict):
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"] = "INFO"
    format: Literal["auto", "json", "console"] = "auto"

    @field_validator("level", mode="before")
    @classmethod
    def _upper(cls, v: Any) -> Any:
        return v.upper() if isinstance(v, str) else v


# ------------------------------------------------------------------------ service
class ServiceConfig(BaseSettings):
    """The whole service configuration (see deploy/config.example.toml)."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter="__",
        case_sensitive=False,
        extra="forbid",
        validate_default=True,
    )

    pack: PackConfig = Field(default_factory=PackConfig)
    can: CanConfig = Field(default_factory=CanConfig)
    estimator: EstimatorConfig = Field(default_factory=EstimatorConfig)
    mqtt: MqttConfig = Field(default_factory=MqttConfig)
    state: StateConfig = Field(default_factory=StateConfig)
    health: HealthConfig = Field(default_factory=HealthConfig)
    logging: LoggingConfig = Field(default_factory=LoggingConfig)

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # The TOML data arrives as init kwargs (see load_config); the
        # environment wins over it. No dotenv / secrets-dir sources.
        return env_settings, init_settings

    def redacted(self) -> dict[str, Any]:
        """A JSON-safe dump with every secret replaced by ``'**********'``."""
        data = self.model_dump(mode="json")
        # SecretStr already dumps masked in JSON mode; be explicit anyway so a
        # future field type change cannot leak.
        if self.mqtt.password is not None:
            data["mqtt"]["password"] = REDACTED
        return data


def _format_loc(loc: tuple[Any, ...]) -> str:
    parts: list[str] = []
    for item in loc:
        if isinstance(item, int):
            parts.append(f"[{item}]")
        elif parts:
            parts.append(f".{item}")
        else:
            parts.append(str(item))
    return "".join(parts) or "<root>"


def _problems(exc: ValidationError) -> list[str]:
    lines: list[str] = []
    for err in exc.errors(include_url=False):
        loc = list(err.get("loc", ()))
        # Drop union/type tags pydantic inserts into the location
        # (e.g. ('mqtt', 'tls', 'function-after[...]') or 'str', 'dict[str,any]').
        loc = [p for p in loc if not (isinstance(p, str) and ("[" in p or p in {"str", "int", "float", "bool"}))]
        msg = str(err.get("msg", "invalid"))
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        inp = err.get("input")
        if err.get("type") not in {"extra_forbidden", "missing", "value_error"} and isinstance(inp, (str, int, float, bool)):
            # Never echo anything that might be the password.
            if not any(isinstance(p, str) and "password" in p.lower() for p in loc):
                msg = f"{msg} (got {inp!r})"
        lines.append(f"{_format_loc(tuple(loc))}: {msg}")
    return lines


def load_config(path: Path | str | None = None) -> ServiceConfig:
    """Load and validate the configuration.

    ``path`` is a TOML file (``None`` = defaults plus environment only).
    Raises :class:`ConfigError` for an unreadable file, a TOML syntax error or
    invalid values, naming each bad field.
    """
    data: dict[str, Any] = {}
    where = "defaults + environment"
    if path is not None:
        p = Path(path)
        where = str(p)
        try:
            with p.open("rb") as fh:
                data = tomllib.load(fh)
        except FileNotFoundError:
            raise ConfigError(f"config file not found: {p}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"invalid TOML in {p}", [str(exc)]) from None
        except OSError as exc:
            raise ConfigError(f"cannot read config file {p}: {exc.strerror or exc}") from None
    problems = _unknown_env_sections(os.environ)
    try:
        cfg = ServiceConfig(**data)
    except ValidationError as exc:
        raise ConfigError(f"invalid configuration ({where}):", problems + _problems(exc)) from None
    except (ValueError, TypeError) as exc:  # e.g. an env value that is not valid JSON for a dict field
        raise ConfigError(f"invalid configuration ({where}):", problems + [str(exc)]) from None
    if problems:
        raise ConfigError(f"invalid configuration ({where}):", problems)
    return cfg


#: ``BMS_*`` variables that are not service settings: the offline tools' data location
#: (``bms_estimator.data.shared_data_dir``) may be set in the same environment.
NON_CONFIG_ENV = frozenset({"BMS_SHARED_DATA"})


def _unknown_env_sections(environ: Mapping[str, str]) -> list[str]:
    """``BMS_*`` variables naming no section (pydantic-settings ignores those)."""
    sections = set(ServiceConfig.model_fields)
    bad = []
    for key in sorted(environ):
        if not key.upper().startswith(ENV_PREFIX) or key.upper() in NON_CONFIG_ENV:
            continue
        section = key[len(ENV_PREFIX) :].split("__", 1)[0].lower()
        if section not in sections:
            bad.append(f"{key} (environment): unknown setting; sections are {', '.join(sorted(sections))}")
    return bad
