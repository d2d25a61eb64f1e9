"""What leaves the service, in one place: MQTT topics, payload keys and units, the Home
Assistant entities, and the CAN status signals.

Every output adapter formats a :class:`~bms_estimator.service.pipeline.Snapshot` with the
functions here (the MQTT publisher, the CAN encoder's status frames, the demo, the
dashboard); nothing else builds a payload.

MQTT topics (``<base>`` = ``mqtt.base_topic``, cells indexed from 0)::

    <base>/<pack_id>/cell/<i>/state    JSON: the keys of CELL_FIELDS (units in their names), "t_s"
    <base>/<pack_id>/pack/state        JSON: the keys of PACK_FIELDS
    <base>/<pack_id>/availability      "online" / "offline", retained (also the last will)
    <discovery_prefix>/sensor/<unique_id>/config   Home Assistant discovery, retained

Non-finite numbers are ``null``. SOC is a fraction 0..1 on MQTT and in percent on CAN.

Adding a per-cell output that the estimator has as an attribute (an SOC uncertainty
``soc_sigma``, say) is one line in :data:`CELL_FIELDS` naming the attribute
(``estimator="soc_sigma"``): the pipeline reads it into every snapshot, and the MQTT payload,
the Home Assistant entity (if ``ha`` is given) and the dashboard follow.
"""

from __future__ import annotations

import enum
import json
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..jsonsafe import json_number

if TYPE_CHECKING:
    from .pipeline import Snapshot

__all__ = [
    "CAN_PACK_SOX_SIGNALS",
    "CAN_STATUS_SIGNALS",
    "PACK_SOX_FIELDS",
    "CELL_FIELDS",
    "PACK_FIELDS",
    "CellField",
    "EstimatorState",
    "Topics",
    "cell_payload_texts",
    "cell_payloads",
    "discovery_messages",
    "pack_payload",
    "soc_stats",
]


class EstimatorState(enum.IntEnum):
    """The service state: the CAN ``EstimatorState`` raw value, the metric's enum, the pack payload's ``state``."""

    INIT = 0  # no SOC yet (before the first sample with a valid current)
    RUNNING = 1
    DEGRADED = 2  # some cells stale or the current invalid
    NO_INPUT = 3  # no sample for a while

    @property
    def label(self) -> str:
        return self.name.lower()


@dataclass(frozen=True)
class CellField:
    """One per-cell output: its payload key (unit in the name), and how Home Assistant shows it."""

    key: str
    name: str  # entity name, after "Cell <i> "
    ha: Mapping[str, Any] | None = None  # discovery keys; None = not discovered
    ha_scale: float = 1.0  # payload value -> displayed unit
    precision: int | None = None  # suggested_display_precision
    uid: str | None = None  # the entity's unique id suffix (default: key); never change a published one
    estimator: str | None = None  # read from this SocEstimator attribute, when it has it (per cell or scalar)


_SOC_HA = {"device_class": "battery", "unit_of_measurement": "%", "state_class": "measurement"}
_DIAG = {"state_class": "measurement", "entity_category": "diagnostic"}

#: per-cell payload keys, in payload order ("t_s" comes last)
CELL_FIELDS: tuple[CellField, ...] = (
    CellField("soc", "SOC", _SOC_HA, 100.0, 1),
    CellField("soc_sigma", "SOC uncertainty", {**_DIAG, "unit_of_measurement": "%", "icon": "mdi:plus-minus"}, 100.0, 1,
              estimator="soc_sigma"),
    CellField("r0_ohm", "R0", {**_DIAG, "unit_of_measurement": "mΩ", "icon": "mdi:resistor"}, 1000.0, 2, "r0"),
    CellField("r1_ohm", "R1"),
    CellField("c1_f", "C1"),
    CellField("r2_ohm", "R2"),
    CellField("c2_f", "C2"),
    CellField("c0_v", "OCV bias"),
    CellField("tau1_s", "tau1"),
    CellField("tau2_s", "tau2"),
    CellField("stale", "stale"),
    CellField("voltage_v", "voltage",
              {"device_class": "voltage", "unit_of_measurement": "V", "state_class": "measurement"}, 1.0, 3, "voltage"),
    CellField("temperature_c", "temperature",
              {"device_class": "temperature", "unit_of_measurement": "°C", "state_class": "measurement"}, 1.0, 1,
              "temperature"),
    CellField("capacity_ah", "capacity", {**_DIAG, "unit_of_measurement": "Ah", "icon": "mdi:battery-high"}, 1.0, 3,
              "capacity"),
    # -1 / +1: the capacity estimate sits at its low / high bound (the stated pack.capacity_ah is wrong for the
    # cell, its SOC unreliable), 0 inside (core.soc.SocEstimator.capacity_at_bound); the pack counts them
    CellField("capacity_at_bound", "capacity at bound", estimator="capacity_at_bound"),
)

#: SOP horizons whose keys the schema names (core.sop.SopConfig's defaults); other configured
#: horizons are published under the same key pattern but have no HA entity or CAN signal, and a
#: horizon named here but not configured has no HA entity (discovery_messages' sop_horizons_s)
SOX_HORIZONS_S: tuple[float, ...] = (2.0, 10.0, 30.0)
_POWER = {"device_class": "power", "unit_of_measurement": "W", "state_class": "measurement"}
_CURRENT = {"device_class": "current", "unit_of_measurement": "A", "state_class": "measurement"}
_ENERGY_LEFT = {"device_class": "energy_storage", "unit_of_measurement": "Wh", "state_class": "measurement"}
_ENERGY_NET = {"device_class": "energy", "unit_of_measurement": "Wh", "state_class": "total"}  # goes down with charge
_ENERGY_OUT = {"device_class": "energy", "unit_of_measurement": "Wh", "state_class": "total_increasing"}
_DURATION = {"device_class": "duration", "unit_of_measurement": "s", "state_class": "measurement"}
_SOH = {**_DIAG, "unit_of_measurement": "%", "icon": "mdi:battery-heart-variant"}


def sox_limit_keys(horizon_s: float) -> tuple[str, str, str, str]:
    """(discharge A, charge A, discharge W, charge W) payload keys of one SOP horizon."""
    tag = f"{horizon_s:g}s"
    return (f"i_discharge_max_{tag}_a", f"i_charge_max_{tag}_a", f"p_discharge_max_{tag}_w", f"p_charge_max_{tag}_w")


def _limit_fields(cls, horizons, *, current_ha: bool, power_ha_all: bool):
    """The SOP fields: currents with an HA entity at 10 s (when ``current_ha``), powers at 10 s or at
    every horizon (``power_ha_all``)."""
    out = []
    for h in horizons:
        ia, ic, pa, pc = sox_limit_keys(h)
        cur = _CURRENT if current_ha and h == 10.0 else None
        pw = _POWER if power_ha_all or h == 10.0 else None
        out += [cls(ia, f"Discharge current limit {h:g} s", cur, 1.0, 1),
                cls(ic, f"Charge current limit {h:g} s", cur, 1.0, 1),
                cls(pa, f"Discharge power limit {h:g} s", pw, 1.0, 0),
                cls(pc, f"Charge power limit {h:g} s", pw, 1.0, 0)]
    return tuple(out)


#: per-cell SOP/SOE/SOH outputs (core.sox.SoxEstimator.outputs); HA entities only for the 10 s power
#: limits, the energy left and the two SOH figures (cell entities are disabled by default anyway)
CELL_SOX_FIELDS: tuple[CellField, ...] = _limit_fields(CellField, SOX_HORIZONS_S, current_ha=False, power_ha_all=False) + (
    CellField("energy_left_wh", "energy left", _ENERGY_LEFT, 1.0, 1),
    CellField("energy_delivered_wh", "energy delivered since full"),
    CellField("energy_discharged_wh", "energy discharged"),
    CellField("time_to_empty_s", "time to empty"),
    CellField("time_to_full_s", "time to full"),
    CellField("soh_capacity", "capacity SOH", _SOH, 100.0, 1),
    CellField("soh_capacity_sigma", "capacity SOH uncertainty"),
    CellField("soh_resistance", "resistance SOH", _SOH, 100.0, 1),
    CellField("r0_ref_ohm", "R0 at reference"),
)
CELL_FIELDS = CELL_FIELDS + CELL_SOX_FIELDS
CELL_KEYS: tuple[str, ...] = tuple(f.key for f in CELL_FIELDS)


@dataclass(frozen=True)
class PackField:
    key: str
    name: str
    ha: Mapping[str, Any] | None = None
    ha_scale: float = 1.0
    precision: int | None = None
    uid: str | None = None


#: pack payload keys, in payload order
PACK_FIELDS: tuple[PackField, ...] = (
    PackField("t_s", "time"),
    PackField("soc_min", "SOC min", _SOC_HA, 100.0, 1),
    PackField("soc_mean", "SOC mean", _SOC_HA, 100.0, 1),
    PackField("soc_max", "SOC max", _SOC_HA, 100.0, 1),
    PackField("current_a", "Current", {"device_class": "current", "unit_of_measurement": "A",
                                       "state_class": "measurement"}, 1.0, 2, "current"),
    PackField("cells_stale", "Stale cells", _DIAG),
    PackField("cells_capacity_at_bound", "Cells at a capacity bound", _DIAG),
    PackField("pack_voltage_v", "Voltage", {"device_class": "voltage", "unit_of_measurement": "V",
                                            "state_class": "measurement"}, 1.0, 2, "voltage"),
    PackField("current_valid", "Current valid"),
    PackField("cells_valid", "Valid cells"),
    PackField("capacity_ah_mean", "Capacity mean", {**_DIAG, "unit_of_measurement": "Ah",
                                                    "icon": "mdi:battery-high"}, 1.0, 3, "capacity"),
    PackField("state", "Estimator state", {"device_class": "enum", "entity_category": "diagnostic",
                                           "options": [s.label for s in EstimatorState]}),
)

#: pack SOP/SOE/SOH outputs (core.sox.SoxEstimator.pack_outputs), appended to the pack payload
PACK_SOX_FIELDS: tuple[PackField, ...] = _limit_fields(PackField, SOX_HORIZONS_S, current_ha=True, power_ha_all=True) + (
    PackField("energy_left_wh", "Energy left", _ENERGY_LEFT, 1.0, 0),
    PackField("energy_delivered_wh", "Energy delivered since full", _ENERGY_NET, 1.0, 1),
    PackField("energy_discharged_wh", "Energy discharged", _ENERGY_OUT, 1.0, 1),
    PackField("time_to_empty_s", "Time to empty", _DURATION, 1.0, 0),
    PackField("time_to_full_s", "Time to full", _DURATION, 1.0, 0),
    PackField("soh_capacity_min", "Capacity SOH (weakest cell)", _SOH, 100.0, 1),
    PackField("soh_resistance_max", "Resistance SOH (weakest cell)", _SOH, 100.0, 1),
)
PACK_FIELDS = PACK_FIELDS + PACK_SOX_FIELDS

#: the unique id suffixes of the Home Assistant entities (``bms_<pack>_pack_<uid>``, ``bms_<pack>_cell<i>_<uid>``):
#: what tells a pack's own discovery configs from those of a pack whose id extends its id ("rack", "rack_pack")
PACK_ENTITY_UIDS: frozenset[str] = frozenset(f.uid or f.key for f in PACK_FIELDS if f.ha is not None)
CELL_ENTITY_UIDS: frozenset[str] = frozenset(f.uid or f.key for f in CELL_FIELDS if f.ha is not None)

#: CAN output message -> {signal: pack SOX key}; sent when the DBC has the message (SI in, the
#: encoder scales to the signal's unit)
CAN_PACK_SOX_SIGNALS: Mapping[str, Mapping[str, str]] = {
    **{f"PackLimits{h:g}s": dict(zip(("DischargeCurrentLimit", "ChargeCurrentLimit", "DischargePowerLimit",
                                       "ChargePowerLimit"), sox_limit_keys(h))) for h in SOX_HORIZONS_S},
    "PackEnergy": {"EnergyLeft": "energy_left_wh", "EnergyDelivered": "energy_delivered_wh",
                   "TimeToEmpty": "time_to_empty_s", "TimeToFull": "time_to_full_s"},
    "PackHealth": {"SohCapacity": "soh_capacity_min", "SohResistance": "soh_resistance_max",
                   "CapacityMean": "capacity_ah_mean", "EnergyDischarged": "energy_discharged_wh"},
}

#: CAN status signal (project DBC) -> the snapshot counter it carries. A DBC whose status
#: messages have a signal not named here is refused when the encoder is built.
CAN_STATUS_SIGNALS: Mapping[str, str] = {
    "UptimeS": "uptime_s",
    "Samples": "samples",
    "DecodeErrors": "decode_errors",
    "Rejections": "rejections",
    "StaleCells": "stale_cells",
    "TimeJumps": "time_jumps",
    "BackwardFrames": "backward_frames",
    "EstimatorState": "estimator_state",
}


# ------------------------------------------------------------------------ figures
@dataclass(frozen=True)
class SocStats:
    """Pack SOC figures over the cells with a finite SOC (all NaN -> NaN, cells -1)."""

    soc_min: float
    soc_mean: float
    soc_max: float
    soc_min_cell: int
    soc_max_cell: int
    n: int


def soc_stats(soc: Any, use: Any = None) -> SocStats:
    """Min/mean/max SOC and their cells, over the cells whose SOC is not NaN (and ``use``
    where given). All NaN -> NaN figures and cells -1."""
    s = np.asarray(soc, dtype=float).reshape(-1)
    ok = ~np.isnan(s)
    if use is not None:
        u = np.asarray(use).reshape(-1)
        if u.size == s.size:
            ok &= u.astype(bool)
    if not ok.any():
        return SocStats(math.nan, math.nan, math.nan, -1, -1, 0)
    idx = np.flatnonzero(ok)
    sv = s[idx]
    imin, imax = int(np.argmin(sv)), int(np.argmax(sv))
    with np.errstate(all="ignore"):
        mean = float(np.mean(np.clip(sv, -1e300, 1e300)))
    return SocStats(float(sv[imin]), mean, float(sv[imax]), int(idx[imin]), int(idx[imax]), int(idx.size))


# ------------------------------------------------------------------------- topics
_HA_ID_BAD = re.compile(r"[^A-Za-z0-9_-]")


@dataclass(frozen=True)
class Topics:
    base_topic: str
    pack_id: str
    discovery_prefix: str = "homeassistant"
    n_cells: int = 0
    cells: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "cells", tuple(f"{self.root}/cell/{i}/state" for i in range(self.n_cells)))

    @property
    def root(self) -> str:
        return f"{self.base_topic}/{self.pack_id}"

    @property
    def pack(self) -> str:
        return f"{self.root}/pack/state"

    @property
    def availability(self) -> str:
        return f"{self.root}/availability"

    @property
    def ha_status(self) -> str:
        return f"{self.discovery_prefix}/status"

    @property
    def ha_id(self) -> str:
        """The pack id as Home Assistant ids allow it ([A-Za-z0-9_-])."""
        return _HA_ID_BAD.sub("_", self.pack_id)

    @property
    def unique_id_prefix(self) -> str:
        """Every discovered entity of this pack has a unique id starting with this."""
        return f"bms_{self.ha_id}_"

    @property
    def probe(self) -> str:
        """A private topic of the service's own (outside ``<base>/<pack_id>/#``; a pack id never starts with '.')."""
        return f"{self.base_topic}/.probe/{self.pack_id}"

    def discovery_filters(self, cells: Iterable[int], *, pack: bool = False) -> list[str]:
        """Subscriptions that see the discovery configs this pack may have left retained, one per unique id it
        may have announced (its pack entities with ``pack``, and those of ``cells``), any component. Not
        ``<prefix>/+/+/config``: that is every config of every device on the broker, and a broker queues at
        most so many messages for a client (Mosquitto's ``max_queued_messages``, 1000 by default) and drops
        the rest: one 96-cell pack announces 1080."""
        base, d = self.unique_id_prefix, self.discovery_prefix
        cell_uids = sorted(CELL_ENTITY_UIDS)
        return ([f"{d}/+/{base}pack_{uid}/config" for uid in sorted(PACK_ENTITY_UIDS)] if pack else []) + [
            f"{d}/+/{base}cell{i}_{uid}/config" for i in cells for uid in cell_uids]


# ----------------------------------------------------------------------- payloads
def _column(key: str, values: Any, n: int) -> list[Any]:
    arr = np.asarray(values)
    if arr.ndim == 0:
        arr = np.broadcast_to(arr, (n,))
    arr = arr.reshape(-1)
    if arr.shape[0] != n:
        raise ValueError(f"{key!r} has {arr.shape[0]} values, expected {n}")
    if key == "stale":
        return arr.astype(bool).tolist()
    values = arr.astype(float)
    out = values.tolist()  # json_number of each value, vectorised: floats, non-finite -> None
    bad = ~np.isfinite(values)
    if bad.any():
        for i in np.flatnonzero(bad).tolist():
            out[i] = None
    return out


def cell_columns(cells: Mapping[str, Any], n: int) -> dict[str, list[Any]]:
    """Per-cell arrays -> JSON-safe columns in payload order (CELL_FIELDS first, then any
    other keys); ``tau*_s`` derived from R*C when absent, ``stale`` False when absent."""
    cols: dict[str, list[Any]] = {}
    for key in [k for k in CELL_KEYS if k in cells] + [k for k in cells if k not in CELL_KEYS and k != "t_s"]:
        cols[key] = _column(key, cells[key], n)
    for tau, (r, c) in (("tau1_s", ("r1_ohm", "c1_f")), ("tau2_s", ("r2_ohm", "c2_f"))):
        if tau not in cols and r in cols and c in cols:
            cols[tau] = [json_number(rv * cv) if rv is not None and cv is not None else None
                         for rv, cv in zip(cols[r], cols[c])]
    if "stale" not in cols:
        cols["stale"] = [False] * n
    order = [k for k in CELL_KEYS if k in cols] + [k for k in cols if k not in CELL_KEYS]
    return {k: cols[k] for k in order}


def cell_payloads(t_s: float, cells: Mapping[str, Any], n: int) -> list[dict[str, Any]]:
    """One JSON-safe payload per cell from per-cell arrays (or scalars)."""
    cols = cell_columns(cells, n)
    t = json_number(t_s)
    out = []
    for i in range(n):
        p = {k: v[i] for k, v in cols.items()}
        p["t_s"] = t
        out.append(p)
    return out


def cell_payload_texts(t_s: float, cells: Mapping[str, Any], n: int, which: Any = None) -> list[str]:
    """The JSON text of each cell's payload (of the cells ``which`` indexes, default all), byte for
    byte ``dumps(cell_payloads(t_s, cells, n)[i])``, in one encoder pass per column.

    Every payload has the same keys in the same order and only numbers, ``null`` and booleans as
    values, so each column is serialised once, ``json.dumps(column)`` (the encoder's own tokens,
    joined by its ``", "`` separator), and each cell's text is a template
    ``{"k_1": %s, ..., "t_s": <t>}`` filled with its row of tokens. 200 cells with the SOX keys
    (36 keys each) and the pack payload: 6.2 ms as 200 dicts and 200 ``dumps`` before, 4.1 ms so
    (fastest of 1,000 runs on the shared 2-core machine; README, Reliability); 3.3 ms of it is
    the encoder's shortest round-trip text of the 7,000 floats, which byte-identical payloads need."""
    if n < 1:
        return []
    cols = cell_columns(cells, n)
    tokens = [json.dumps(col, allow_nan=False)[1:-1].split(", ") for col in cols.values()]
    head = ", ".join(json.dumps(k).replace("%", "%%") + ": %s" for k in cols)
    template = "{" + head + ", " + json.dumps("t_s") + ": " + json.dumps(json_number(t_s)).replace("%", "%%") + "}"
    rows = list(zip(*tokens))
    idx = range(n) if which is None else np.asarray(which).reshape(-1).tolist()
    return [template % rows[i] for i in idx]


def snapshot_cell_payloads(snap: Snapshot) -> list[dict[str, Any]]:
    return cell_payloads(snap.t_s, {**snap.cells, "stale": ~snap.valid}, snap.n_cells)


def snapshot_cell_payload_texts(snap: Snapshot, which: Any = None) -> list[str]:
    """:func:`cell_payload_texts` of a snapshot: ``dumps`` of each of :func:`snapshot_cell_payloads`."""
    return cell_payload_texts(snap.t_s, {**snap.cells, "stale": ~snap.valid}, snap.n_cells, which)


def pack_payload(snap: Snapshot) -> dict[str, Any]:
    """The pack payload of a snapshot (JSON-safe)."""
    st = snap.soc
    return {
        "t_s": json_number(snap.t_s),
        "soc_min": json_number(st.soc_min),
        "soc_mean": json_number(st.soc_mean),
        "soc_max": json_number(st.soc_max),
        "current_a": json_number(snap.current_a),
        "cells_stale": snap.n_cells - snap.cells_valid,
        "cells_capacity_at_bound": getattr(snap, "cells_capacity_at_bound", 0),  # a wrong stated capacity
        "pack_voltage_v": json_number(snap.pack_voltage_v),
        "current_valid": bool(snap.current_valid),
        "cells_valid": snap.cells_valid,
        "capacity_ah_mean": json_number(snap.capacity_ah_mean),
        "state": snap.state.label,
        **{k: json_number(v) for k, v in getattr(snap, "pack_sox", {}).items()},  # SOP/SOE/SOH when computed
    }


def dumps(payload: Mapping[str, Any]) -> str:
    return json.dumps(payload, allow_nan=False)


# ---------------------------------------------------------------------- discovery
def _template(key: str, scale: float) -> str:
    if scale == 1.0:
        return f"{{{{ value_json.{key} if value_json.{key} is number else none }}}}"
    return f"{{{{ value_json.{key} * {scale:g} if value_json.{key} is number else none }}}}"


def discovery_messages(
    topics: Topics, *, sw_version: str, expire_after_s: float | None = None,
    sop_horizons_s: Any = SOX_HORIZONS_S,
) -> list[tuple[str, str]]:
    """Home Assistant discovery (topic, JSON config) pairs for the pack and every cell.

    Pack entities are enabled; per-cell entities are disabled by default (a 200-cell pack
    would otherwise add a thousand), and each is unavailable while its cell is stale. The SOP
    limit entities are those of the horizons both named here (:data:`SOX_HORIZONS_S`) and
    configured (``sop_horizons_s``, ``estimator.sop.horizons_s``): another horizon's keys are
    never in a payload, and its entity would read "unknown" for ever.
    """
    configured = {k for h in sop_horizons_s for k in sox_limit_keys(float(h))}
    unpublished = {k for h in SOX_HORIZONS_S for k in sox_limit_keys(h)} - configured
    pid = topics.ha_id
    device = {
        "identifiers": [f"bms_estimator_{pid}"],
        "name": f"Battery pack {pid}",
        "manufacturer": "bms-estimator",
        "model": "ECM + SOC estimator",
        "sw_version": sw_version,
    }
    origin = {"name": "bms-estimator", "sw_version": sw_version}
    out: list[tuple[str, str]] = []

    def add(uid: str, name: str, state_topic: str, key: str, ha: Mapping[str, Any], scale: float,
            precision: int | None, **extra: Any) -> None:
        cfg: dict[str, Any] = {
            "name": name,
            "unique_id": uid,
            "state_topic": state_topic,
            "value_template": (f"{{{{ value_json.{key} }}}}" if ha.get("device_class") == "enum"
                               else _template(key, scale)),
            "device": device,
            "origin": origin,
            **ha,
            **extra,
        }
        if precision is not None:
            cfg["suggested_display_precision"] = precision
        if "availability" not in cfg:  # availability_topic and availability exclude each other
            cfg.update(availability_topic=topics.availability, payload_available="online",
                       payload_not_available="offline")
        out.append((f"{topics.discovery_prefix}/sensor/{uid}/config", json.dumps(cfg)))

    for f in PACK_FIELDS:
        if f.ha is not None and f.key not in unpublished:
            add(f"{topics.unique_id_prefix}pack_{f.uid or f.key}", f.name, topics.pack, f.key, f.ha, f.ha_scale, f.precision)
    for i, topic in enumerate(topics.cells):
        stale = {
            "availability": [
                {"topic": topics.availability},
                {"topic": topic, "value_template": "{{ 'offline' if value_json.stale else 'online' }}"},
            ],
            "availability_mode": "all",
            "enabled_by_default": False,
        }
        if expire_after_s is not None:
            stale["expire_after"] = max(1, int(round(expire_after_s)))
        for f in CELL_FIELDS:
            if f.ha is not None and f.key not in unpublished:
                uid = f"{topics.unique_id_prefix}cell{i}_{f.uid or f.key}"
                add(uid, f"Cell {i} {f.name}", topic, f.key, f.ha, f.ha_scale, f.precision, **stale)
    return out
