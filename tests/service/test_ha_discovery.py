"""Every Home Assistant discovery config the service publishes, checked against Home Assistant's own rules
(no Home Assistant installed: the rules are copied here from its source, home-assistant/core):

* ``homeassistant/components/sensor/const.py``: ``DEVICE_CLASS_UNITS`` (the units a device class takes) and
  ``DEVICE_CLASS_STATE_CLASSES`` (its state classes), below for the device classes this project uses;
  ``NON_NUMERIC_DEVICE_CLASSES`` (date, enum, timestamp: no unit, no state class). A unit outside the set is
  refused by the MQTT sensor's schema (the entity is not created); a state class outside it logs "is using
  state class ... which is impossible considering device class" and records no statistics.
* ``homeassistant/components/mqtt/sensor.py``, ``validate_sensor_state_and_device_class_config``: ``options``
  only with device class ``enum`` and never with ``state_class`` or ``unit_of_measurement``;
  ``expire_after`` and ``suggested_display_precision`` are ``cv.positive_int`` (an integer >= 0).
* ``homeassistant/components/mqtt/discovery.py``, ``TOPIC_MATCHER``: ``<component>/[<node_id>/]<object_id>/config``
  with ``[a-zA-Z0-9_-]`` ids; ``availability`` and ``availability_topic`` exclude each other (``vol.Exclusive``
  in the MQTT availability schema).

And what Home Assistant cannot check: every ``value_template`` and availability template reads a key the
state payload on its ``state_topic`` really has (else the entity reads "unknown" for ever), the
availability topic is the one the publisher keeps retained with its last will (test_mqtt.py:
``test_states_arrive_as_json_with_availability``, ``test_last_will_when_publisher_process_is_killed``), and unique ids are unique
across cells and packs.
"""

from __future__ import annotations

import json
import re

import pytest

from bms_estimator.can.decoder import FrameDecoder
from bms_estimator.can.sampler import SampleAssembler
from bms_estimator.core.soc import SocEstimator
from bms_estimator.core.sop import SopConfig
from bms_estimator.core.sox import SoxConfig, SoxEstimator
from bms_estimator.service import schema
from bms_estimator.service.config import MqttConfig
from bms_estimator.service.mqtt import MqttPublisher
from bms_estimator.service.pipeline import Pipeline

from test_daemon import CAPACITY_AH, DB, N, current_frame, ocv, restamp, voltage_frame

# homeassistant/components/sensor/const.py (UnitOfEnergy, UnitOfPower, ... spelled out from
# homeassistant/const.py), for the device classes the project publishes
HA_DEVICE_CLASS_UNITS = {
    "battery": {"%"},
    "current": {"A", "mA", "µA"},
    "duration": {"d", "h", "min", "s", "ms", "µs"},
    "energy": {"J", "kJ", "MJ", "GJ", "mWh", "Wh", "kWh", "MWh", "GWh", "TWh", "cal", "kcal", "Mcal", "Gcal"},
    "energy_storage": {"J", "kJ", "MJ", "GJ", "mWh", "Wh", "kWh", "MWh", "GWh", "TWh", "cal", "kcal", "Mcal",
                       "Gcal"},
    "power": {"mW", "W", "kW", "MW", "GW", "TW", "BTU/h"},
    "temperature": {"°C", "°F", "K"},
    "voltage": {"V", "mV", "µV", "kV", "MV"},
}
HA_DEVICE_CLASS_STATE_CLASSES = {
    "battery": {"measurement"},
    "current": {"measurement"},
    "duration": {"measurement", "total", "total_increasing"},
    "energy": {"total", "total_increasing"},
    "energy_storage": {"measurement"},
    "enum": set(),
    "power": {"measurement"},
    "temperature": {"measurement"},
    "voltage": {"measurement"},
}
HA_NON_NUMERIC_DEVICE_CLASSES = {"date", "enum", "timestamp"}
HA_STATE_CLASSES = {"measurement", "total", "total_increasing"}
HA_TOPIC_MATCHER = re.compile(r"(?P<component>\w+)/(?:(?P<node_id>[a-zA-Z0-9_-]+)/)?(?P<object_id>[a-zA-Z0-9_-]+)/config")
HA_ENTITY_CATEGORIES = {"config", "diagnostic"}

_KEY = re.compile(r"value_json\.(\w+)")


def _snapshot(horizons_s=None):
    """A snapshot of the service's pipeline (6 cells, SOP/SOE/SOH on) after a few seconds of frames."""
    snaps = []
    sop = SopConfig() if horizons_s is None else SopConfig(horizons_s=tuple(horizons_s))
    pipe = Pipeline(FrameDecoder(DB, "default", N), SampleAssembler(N, 1.0, 2.5),
                    SocEstimator(N, ocv(), CAPACITY_AH, 1.0), on_snapshot=snaps.append,
                    sox=SoxEstimator(N, 1.0, SoxConfig(sop=sop)), clock=lambda: 0.0, wall_clock=lambda: 0.0)
    frames = []
    for k in range(40):
        t = 100.0 + 0.1 * k
        frames.append(current_frame(t, -1.0))
        for base in range(0, N, 3):
            frames.append(voltage_frame(t + 0.002, base, [3.6, 3.61, 3.62][: N - base]))
    for f in restamp(frames + [current_frame(104.0, -1.0)]):
        pipe.process_frame(f)
    return snaps[-1]


def _configs(pack_id: str, n: int, **kw) -> dict[str, dict]:
    pub = MqttPublisher(MqttConfig(host="127.0.0.1"), pack_id, n, expire_after_s=30, **kw)
    return {topic: json.loads(text) for topic, text in pub.discovery_messages()}


def _check_ha_rules(topic: str, cfg: dict) -> None:
    m = HA_TOPIC_MATCHER.fullmatch(topic.split("/", 1)[1])
    assert m is not None and m["component"] == "sensor", topic
    assert m["object_id"] == cfg["unique_id"], topic
    dc, unit, sc = cfg.get("device_class"), cfg.get("unit_of_measurement"), cfg.get("state_class")
    if dc in HA_NON_NUMERIC_DEVICE_CLASSES:
        assert unit is None and sc is None, topic
    if dc is not None:
        assert dc in HA_DEVICE_CLASS_STATE_CLASSES, f"{topic}: device class {dc!r} not checked here"
        if unit is not None:
            assert unit in HA_DEVICE_CLASS_UNITS[dc], f"{topic}: unit {unit!r} not allowed for {dc!r}"
        if sc is not None:
            assert sc in HA_DEVICE_CLASS_STATE_CLASSES[dc], f"{topic}: state class {sc!r} impossible for {dc!r}"
    if sc is not None:
        assert sc in HA_STATE_CLASSES, topic
    if "options" in cfg:
        assert dc == "enum" and cfg["options"] and sc is None and unit is None, topic
    for key in ("expire_after", "suggested_display_precision"):
        if key in cfg:
            assert isinstance(cfg[key], int) and not isinstance(cfg[key], bool) and cfg[key] >= 0, topic
    assert not ("availability" in cfg and "availability_topic" in cfg), topic
    assert cfg.get("entity_category", "diagnostic") in HA_ENTITY_CATEGORIES, topic
    assert cfg["device"]["identifiers"] and cfg["origin"]["name"], topic


@pytest.mark.parametrize("horizons_s", [None, (5.0, 60.0), (10.0,)], ids=["default", "5-60s", "10s"])
def test_discovery_follows_home_assistants_rules_and_reads_published_keys(horizons_s):
    """Every config passes Home Assistant's checks, and every template reads a key of the payload published
    on its state topic: with the default SOP horizons and with others (``estimator.sop.horizons_s``).
    Before, the 2, 10 and 30 s limit entities were announced whatever the horizons, and with 5 and 60 s
    they read keys no payload has (12 pack and 12 per-cell entities "unknown" for ever)."""
    snap = _snapshot(horizons_s)
    cell_keys = set(schema.snapshot_cell_payloads(snap)[0])
    pack_keys = set(schema.pack_payload(snap))
    kw = {} if horizons_s is None else {"sop_horizons_s": horizons_s}
    configs = _configs("pk", N, **kw)
    topics = schema.Topics("bms", "pk", n_cells=N)
    payload_keys = {topics.pack: pack_keys, **{t: cell_keys for t in topics.cells}}
    assert configs
    for topic, cfg in configs.items():
        _check_ha_rules(topic, cfg)
        keys = payload_keys[cfg["state_topic"]]
        read = set(_KEY.findall(cfg["value_template"]))
        assert read and read <= keys, f"{topic} reads {read - keys}, not in the payload on {cfg['state_topic']}"
        for av in cfg.get("availability", []):
            if "value_template" in av:
                assert set(_KEY.findall(av["value_template"])) <= payload_keys[av["topic"]], topic
        # the pack's availability: the retained topic the publisher keeps, with its last will
        avail = cfg.get("availability_topic") or cfg["availability"][0]["topic"]
        assert avail == topics.availability
    # the configured horizons the schema names keep their entities (10 s: pack and cells)
    if 10.0 in (horizons_s or schema.SOX_HORIZONS_S):
        assert "homeassistant/sensor/bms_pk_pack_p_discharge_max_10s_w/config" in configs
        assert "homeassistant/sensor/bms_pk_cell0_p_charge_max_10s_w/config" in configs


def test_unique_ids_are_unique_and_stable_across_cells_and_packs():
    """Two packs of 3 and 12 cells: no unique id or discovery topic twice, every unique id starting with its
    pack's prefix, and the ids of a published entity unchanged (``bms_<pack>_cell<i>_soc``)."""
    a, b = _configs("packA", 3), _configs("packB", 12)
    uids = [c["unique_id"] for c in (*a.values(), *b.values())]
    assert len(uids) == len(set(uids)) and not set(a) & set(b)
    assert all(c["unique_id"].startswith("bms_packA_") for c in a.values())
    assert "homeassistant/sensor/bms_packB_cell11_soc/config" in b
    assert {c["device"]["identifiers"][0] for c in b.values()} == {"bms_estimator_packB"}
    # what tells pack "rack"'s entities from pack "rack_pack"'s (MqttPublisher._is_ours, the orphan removal)
    for uid in schema.PACK_ENTITY_UIDS | schema.CELL_ENTITY_UIDS:
        assert not re.search(r"(^|_)(pack|cell\d+)_", uid), uid
