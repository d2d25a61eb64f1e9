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

import dataclasses
import difflib
import ipaddress
import json
import os
import re
import tomllib
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    PrivateAttr,
    ValidationInfo,
    create_model,
    field_validator,
    model_validator,
)
from pydantic_settings import (BaseSettings, NestedSecretsSettingsSource, PydanticBaseSettingsSource, SettingsConfigDict,
                               SettingsError)

from ..core.identifier import IdentifierConfig
from ..core.soc_ekf import SocEkfConfig
from ..core.sop import SopConfig
from ..core.sox import SoxConfig
from ..errors import ConfigError
from ..core.soc import SocConfig

__all__ = [
    "CanConfig",
    "CanOutputConfig",
    "ConfigError",
    "EstimatorConfig",
    "ID_PATTERN",
    "HealthConfig",
    "LoggingConfig",
    "MAX_CELLS",
    "MqttConfig",
    "PackConfig",
    "ServiceConfig",
    "StateConfig",
    "TlsConfig",
    "check_topic_part",
    "load_config",
    "soc_config_from_core",
]

ENV_PREFIX = "BMS_"
REDACTED = "**********"

_TOPIC_FORBIDDEN = set("+#\x00")
#: a pack id (an MQTT topic level and a Home Assistant id part): the service's and the dashboard's rule
ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_default=True, allow_inf_nan=False)  # NaN is not "> 100000"


# --------------------------------------------------------------------------- pack
#: the most cells a pack may have (``pack.n_cells``)
MAX_CELLS = 1024


class PackConfig(_Strict):
    pack_id: str = Field("pack0", pattern=ID_PATTERN, description="used in MQTT topics and HA ids")
    n_cells: int = Field(16, ge=1, le=MAX_CELLS)
    capacity_ah: float = Field(50.0, gt=0, le=1e5)
    ocv_csv: Path | list[Path] | None = Field(
        None, description="OCV(SOC) table, or a list of tables at several temperatures (each with its temperature_c "
                          "column, from 'bms-estimator ocv'), read at each cell's temperature; None = built-in sample curve")


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
    dbc: Path | None = Field(None, description="None = the project's DBC (an 18650's ranges); \"large-cell\" = its "
                             "variant for cells of 20 Ah and up (bms_estimator.can.dbc); else a DBC file")
    # Input mapping: preset name ("default", "foxbms"), a TOML file path, or an
    # inline table; validated by bms_estimator.can.mapping.load_mapping.
    mapping: str | dict[str, Any] = "default"
    kernel_filters: bool = Field(True, description="receive only the mapped frame ids (kernel filters on socketcan)")
    output: CanOutputConfig = Field(default_factory=CanOutputConfig)

    @field_validator("interface")
    @classmethod
    def _known_interface(cls, v: str) -> str:
        import can

        if v not in can.VALID_INTERFACES:
            raise ValueError(f"unknown CAN interface {v!r}; python-can knows "
                             f"{', '.join(sorted(can.VALID_INTERFACES))}")
        return v

    def channel_problem(self) -> str | None:
        """Why the channel cannot be opened here, where that can be told without opening it
        (a socketcan network interface that does not exist); None otherwise."""
        if self.interface == "socketcan" and isinstance(self.channel, str) and self.channel:
            if not os.path.exists(os.path.join("/sys/class/net", self.channel)):
                return f"no network interface {self.channel!r} here (ip link show {self.channel})"
        return None

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
def _dataclass_fields(cls: type) -> dict[str, tuple[Any, Any]]:
    """``{name: (annotation with its bounds, default)}`` of a core config dataclass."""
    hints = typing.get_type_hints(cls, include_extras=True)
    out: dict[str, tuple[Any, Any]] = {}
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        out[f.name] = (hints[f.name], default)
    return out


_IDENTIFIER_FIELDS = _dataclass_fields(IdentifierConfig)
_SOC_FIELDS = _dataclass_fields(SocConfig)
_EKF_FIELDS = _dataclass_fields(SocEkfConfig)
_SOP_FIELDS = _dataclass_fields(SopConfig)

#: ``[estimator.core.identifier]``: the fields of the core's IdentifierConfig, with its bounds
IdentifierSettings = create_model("IdentifierSettings", __base__=_Strict, **_IDENTIFIER_FIELDS)  # type: ignore[call-overload]
#: ``[estimator.core.ekf]``: the noise model of the EKF SOC method (core.soc_ekf.SocEkfConfig)
EkfSettings = create_model("EkfSettings", __base__=_Strict, **_EKF_FIELDS)  # type: ignore[call-overload]


class _CoreBase(_Strict):
    _soc_config: SocConfig = PrivateAttr(default_factory=SocConfig)

    @model_validator(mode="after")
    def _build(self) -> Any:
        given = self.model_fields_set
        ident = {k: getattr(self, k) for k in _IDENTIFIER_FIELDS if k in given}
        ident.update({k: getattr(self.identifier, k) for k in self.identifier.model_fields_set})
        soc = {k: getattr(self, k) for k in _SOC_FIELDS}
        ekf = SocEkfConfig(**{k: getattr(self.ekf, k) for k in self.ekf.model_fields_set})
        self._soc_config = SocConfig(identifier=IdentifierConfig(**ident), ekf=ekf, **soc)  # ValueError: a cross-field rule
        return self


#: ``[estimator.core]``: one definition, the core's dataclasses. Every field of SocConfig,
#: and every field of IdentifierConfig either here (flat) or in an ``identifier`` table.
CoreSettings = create_model(  # type: ignore[call-overload]
    "CoreSettings",
    __base__=_CoreBase,
    identifier=(IdentifierSettings, Field(default_factory=IdentifierSettings)),
    ekf=(EkfSettings, Field(default_factory=EkfSettings)),
    **_SOC_FIELDS,
    **_IDENTIFIER_FIELDS,
)


class _SopBase(_Strict):
    _sop_config: SopConfig = PrivateAttr(default_factory=SopConfig)

    @model_validator(mode="after")
    def _build(self) -> Any:
        self._sop_config = SopConfig(**{k: getattr(self, k) for k in _SOP_FIELDS})  # ValueError: a cross-field rule
        return self


#: ``[estimator.sop]``: the cell's voltage and current limits, derating and SOP horizons (core.sop.SopConfig)
SopSettings = create_model("SopSettings", __base__=_SopBase, **_SOP_FIELDS)  # type: ignore[call-overload]


class EstimatorConfig(_Strict):
    sample_period_s: float = Field(1.0, gt=0, le=60)
    staleness_s: float = Field(5.0, gt=0, le=3600)
    # The numerical core's tuning: the fields of core.soc.SocConfig and core.identifier.IdentifierConfig.
    core: CoreSettings = Field(default_factory=CoreSettings)  # type: ignore[valid-type]
    # State of power, energy and health (core/sox.py): the cell's limits and the SOP horizons.
    sop: SopSettings = Field(default_factory=SopSettings)  # type: ignore[valid-type]

    @property
    def sox_config(self) -> SoxConfig:
        """``sop`` as the core's :class:`~bms_estimator.core.sox.SoxConfig`."""
        return SoxConfig(sop=self.sop._sop_config)

    @property
    def soc_config(self) -> SocConfig:
        """``core`` as the core's :class:`~bms_estimator.core.soc.SocConfig`."""
        return self.core._soc_config


def _bounds_text(annotation: Any) -> str:
    if typing.get_origin(annotation) is Literal:
        return "one of " + ", ".join(str(a) for a in typing.get_args(annotation))
    parts = []
    for meta in getattr(annotation, "__metadata__", ()):
        for attr, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            v = getattr(meta, attr, None)
            if v is not None:
                parts.append(f"{op} {v:g}")
    return ", ".join(parts)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def core_example_toml() -> str:
    """The ``[estimator.core]`` section of deploy/config.example.toml, made from the core's
    dataclasses (every field, its default and its bounds)."""
    lines = [
        "[estimator.core]",
        "# The numerical core's tuning: the fields of SocConfig (core/soc.py) and IdentifierConfig",
        "# (core/identifier.py), with their defaults and bounds; the identifier's fields may also go",
        "# in an [estimator.core.identifier] table. Unknown names are rejected. Made by",
        "# bms_estimator.service.config.core_example_toml(); the defaults serve both measured cells.",
    ]
    for name, (annotation, default) in {**_SOC_FIELDS, **_IDENTIFIER_FIELDS}.items():
        entry = f"# {name} = {_toml_value(default)}"
        bounds = _bounds_text(annotation)
        lines.append(f"{entry:<38}  # {bounds}" if bounds else entry)
    lines += ["", "[estimator.core.ekf]", "# The EKF SOC method's noise model (core/soc_ekf.py, SocEkfConfig)."]
    for name, (annotation, default) in _EKF_FIELDS.items():
        entry = f"# {name} = {_toml_value(default)}"
        bounds = _bounds_text(annotation)
        lines.append(f"{entry:<38}  # {bounds}" if bounds else entry)
    return "\n".join(lines) + "\n"


def soc_config_from_core(core: Mapping[str, Any]) -> SocConfig:
    """An ``[estimator.core]`` table -> :class:`SocConfig`; raises :class:`ConfigError` naming
    each bad field (``estimator.core.<field>: ...``)."""
    try:
        return EstimatorConfig(core=core).soc_config
    except ValidationError as exc:
        raise ConfigError("invalid configuration:", ["estimator." + p for p in _problems(exc)]) from None


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


def check_topic_part(value: str, *, allow_empty: bool = False) -> str:
    """``value`` as a part of an MQTT topic (no wildcard ``+`` / ``#`` or NUL, no empty level), else a
    ``ValueError``; the service's rule for ``mqtt.base_topic``, and the dashboard's for ``--base-topic``."""
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
    qos: int = Field(0, ge=0, le=2, description="QoS of the state payloads; discovery and availability are QoS 1, retained")
    publish_period_s: float = Field(0.0, ge=0, le=3600, description="shortest time between two states of a topic (frame time); 0 = every sample")
    soc_deadband: float = Field(0.0, ge=0, le=1, description="a cell whose SOC moved less than this (fraction) and whose stale flag is unchanged is not re-sent ...")
    max_period_s: float = Field(60.0, gt=0, le=86400, description="... for longer than this")
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
        return check_topic_part(v)

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
    # A year, not a week: the estimator rests over any gap (core.soc's rest: the RC voltages decay, the SOC's
    # variance grows, a rest reading replaces the count), so a parked month is a rest, not a reason to forget.
    # At 7 days a vehicle parked a fortnight started fresh: its learnt capacity, the commissioning R0 its
    # resistance SOH is measured against, and its energy counters gone.
    max_age_s: float | None = Field(366 * 86400.0, gt=0, description="older saved state is ignored (and one saved this far ahead of the clock); None = no limit")

    def path_problem(self) -> str | None:
        """Why no state can ever be saved at ``path``, where that can be told without writing: it is a
        directory (which the service would set aside as a corrupt state file), or the nearest part of
        it that exists is a file; None otherwise (missing directories are made by the first save)."""
        try:
            if self.path.is_dir():
                return f"{self.path} is a directory: name the state file in it (e.g. {self.path / 'state.npz'})"
            existing = next((p for p in self.path.parents if p.exists()), None)
        except OSError:  # not ours to tell (permissions): the saves say so
            return None
        if existing is not None and not existing.is_dir():
            return f"{existing} is not a directory"
        return None


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
    cell_metrics: bool = Field(False, description="per-cell gauges (SOC, R0, capacity, the 10 s power limit each way) in /metrics: 5 series per cell")

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
def secrets_dir(environ: Mapping[str, str] | None = None) -> Path | None:
    """Where secret files are read: ``$CREDENTIALS_DIRECTORY`` (systemd's ``LoadCredential=``)."""
    env = os.environ if environ is None else environ
    d = env.get("CREDENTIALS_DIRECTORY", "").split(":")[0]
    return Path(d) if d else None


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
        # The TOML data arrives as init kwargs (see load_config); secret files win over it,
        # and the environment over both. No dotenv. A secret file holds one setting and is
        # named ``<section>__<key>`` (``mqtt__password``: ``BMS_MQTT__PASSWORD`` without the
        # prefix; a trailing newline is dropped). Under systemd, ``LoadCredential=
        # mqtt__password:/etc/bms-estimator/mqtt_password`` puts it in $CREDENTIALS_DIRECTORY,
        # readable by the service alone.
        secrets = NestedSecretsSettingsSource(
            file_secret_settings, secrets_dir=secrets_dir(), secrets_dir_missing="ok", secrets_prefix="",
            secrets_nested_delimiter="__",
        )
        return env_settings, secrets, init_settings

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
        if err.get("type") == "extra_forbidden" and loc:
            near = difflib.get_close_matches(str(loc[-1]), _known_keys(loc[:-1]), n=1, cutoff=0.6)
            if near:
                msg = f"{msg} (did you mean '{near[0]}'?)"
        lines.append(f"{_format_loc(tuple(loc))}: {msg}")
    return lines


def _known_keys(loc: list[Any]) -> list[str]:
    """The keys the section at ``loc`` takes (its model's fields), or none where ``loc`` is not a model."""
    model: Any = ServiceConfig
    for part in loc:
        field = getattr(model, "model_fields", {}).get(part)
        if field is None:
            return []
        ann = field.annotation
        model = next((c for c in (ann, *typing.get_args(ann))
                      if isinstance(c, type) and issubclass(c, BaseModel)), None)
        if model is None:
            return []
    return list(getattr(model, "model_fields", {}))


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
        except UnicodeDecodeError as exc:  # TOML is UTF-8; without this the message named neither file nor byte
            raise ConfigError(f"invalid TOML in {p}", [f"not UTF-8 text: {exc.reason} at byte {exc.start}"]) from None
        except OSError as exc:
            raise ConfigError(f"cannot read config file {p}: {exc.strerror or exc}") from None
    problems = _unknown_env_sections(os.environ)
    try:
        cfg = ServiceConfig(**data)
    except ValidationError as exc:
        raise ConfigError(f"invalid configuration ({where}):", problems + _problems(exc)) from None
    except SettingsError as exc:  # a value pydantic-settings could not parse: its source is at fault, not the file
        source, lines = _settings_error_problems(exc, os.environ)
        raise ConfigError(f"invalid configuration ({source}):", problems + lines) from None
    except (ValueError, TypeError) as exc:  # e.g. an env value that is not valid JSON for a dict field
        raise ConfigError(f"invalid configuration ({where}):", problems + [str(exc)]) from None
    if problems:
        raise ConfigError(f"invalid configuration ({where}):", problems)
    return cfg


def _settings_error_problems(exc: SettingsError, environ: Mapping[str, str]) -> tuple[str, list[str]]:
    """(where, problem lines) of pydantic-settings' 'error parsing value for field "estimator" from source
    "EnvSettingsSource"': the ``BMS_`` variables of that section, the one whose value is not JSON where one is
    found (a list or table value is read as JSON), never their values (one may be a password)."""
    why = str(exc.__cause__ or exc).strip().splitlines()[0]
    m = re.search(r'field "([^"]+)" from source "(\w+)"', str(exc))
    field, source = (m.group(1), m.group(2)) if m else ("", "")
    if source == "EnvSettingsSource":
        head = f"{ENV_PREFIX}{field}".upper()
        keys = sorted(k for k in environ if k.upper() == head or k.upper().startswith(head + "__"))

        def not_json(key: str) -> bool:
            try:
                json.loads(environ[key])
            except ValueError:
                return environ[key].lstrip()[:1] in ("[", "{")
            return False

        keys = [k for k in keys if not_json(k)] or keys
        what = f"not valid JSON ({why})" if isinstance(exc.__cause__, json.JSONDecodeError) else why
        return "environment", [f"{', '.join(keys) or head} (environment): {what}"]
    if "Secrets" in source:
        return f"secret files in {secrets_dir()}", [f"{field}: {why}"]
    return source or "settings", [f"{field or '<root>'}: {why}"]


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
