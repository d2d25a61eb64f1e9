"""The service's Prometheus metrics (prometheus_client), one registry per service.

What the service itself measures is instrumented directly (histograms of the tick time, the
loop lag and the MQTT publish latency; MQTT and state-file counters; the state as an Enum).
What other components count (decoder, sampler, bus, estimator) and the battery figures of
the last :class:`~bms_estimator.service.pipeline.Snapshot` are read when scraped, by
:class:`_ServiceCollector`, so ``/metrics`` is current even while no sample comes.

Families (``bms_`` prefix; counters end in ``_total``):

* input: ``can_frames_received``, ``can_frames_decoded``, ``can_frames_ignored{reason}``,
  ``decode_problems{reason}``, ``samples``, ``samples_current_invalid``,
  ``sample_anomalies{kind}``, ``cell_samples_stale``, ``tick_errors``
* CAN bus: ``can_bus_up``, ``can_bus_events{event}``, ``can_rx_dropped{reason}`` (``queue_full``: the
  receive thread's bounded queue; ``malformed``; ``kernel``: the socket buffer, from ``SO_RXQ_OVFL`` on
  socketcan and ``/proc/net/udp`` on udp_multicast), ``can_rx_backlog``, ``can_rx_error_frames``,
  ``can_tx_frames``, ``can_tx_dropped``, ``can_tx_errors``, ``can_encode_problems{kind}``
* estimator: ``estimator_state{bms_estimator_state}`` (Enum), ``estimator_rejections``,
  ``estimator_corrections``, ``estimator_restarts``, ``estimator_rests`` and ``estimator_rest_seconds``
  (gaps without samples rested over: a time jump, a restart), ``state_restored``, ``tick_seconds``
  (histogram), ``last_sample_time_seconds``
* battery: ``pack_soc{stat=min|mean|max}``, ``pack_current_amperes``, ``pack_voltage_volts``,
  ``pack_capacity_ah``, ``cells_stale``, ``cells_capacity_at_bound`` (cells whose capacity estimate sits at a
  bound: ``pack.capacity_ah`` is wrong for them); SOP/SOE/SOH: ``pack_current_limit_amperes`` and
  ``pack_power_limit_watts{direction=discharge|charge,horizon=2s|10s|30s}``, ``pack_energy_left_wh``,
  ``pack_energy_delivered_wh``, ``pack_energy_discharged_wh``, ``pack_time_to_empty_seconds``,
  ``pack_time_to_full_seconds``, ``pack_soh_ratio{kind=capacity|resistance}``; and with ``health.cell_metrics``
  ``cell_soc{cell}``, ``cell_r0_ohms{cell}``, ``cell_capacity_ah{cell}``, ``cell_power_limit_watts{cell,direction}``
  (5 series per cell)
* outputs: ``mqtt_published``, ``mqtt_dropped``, ``mqtt_connects``, ``mqtt_connect_failures``,
  ``mqtt_connected``, ``mqtt_publish_latency_seconds`` (histogram), ``state_saves``,
  ``state_save_errors``
* liveness: ``healthy``, ``heartbeat_age_seconds``, ``loop_lag_seconds`` (histogram)
* the library's ``process_*``, ``python_info`` and ``bms_build_info``.
"""

from __future__ import annotations

import math
import platform
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
from prometheus_client import (
    CollectorRegistry,
    Counter,
    Enum,
    Gauge,
    Histogram,
    Info,
    PlatformCollector,
    ProcessCollector,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from .. import package_version
from .schema import EstimatorState

if TYPE_CHECKING:
    from .daemon import Service

__all__ = ["ServiceMetrics", "package_version"]

#: tick time: 0.1 ms .. 1 s (a 2000-cell tick with every output is tens of ms)
_TICK_BUCKETS = (1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0)
_LAG_BUCKETS = (1e-3, 5e-3, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5)
_PUBLISH_BUCKETS = (1e-3, 5e-3, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


class ServiceMetrics:
    """The metrics of one service; ``registry`` is what ``/metrics`` exposes."""

    def __init__(self, *, cell_metrics: bool = False, registry: CollectorRegistry | None = None) -> None:
        self.registry = r = registry if registry is not None else CollectorRegistry()
        self.cell_metrics = cell_metrics
        ProcessCollector(registry=r)
        PlatformCollector(registry=r)
        Info("bms_build", "bms-estimator build", registry=r).info(
            {"version": package_version(), "python": platform.python_version()})
        self.estimator_state = Enum("bms_estimator_state", "state of the estimator service", registry=r,
                                    states=[s.label for s in EstimatorState])
        self.tick_seconds = Histogram("bms_tick_seconds", "processing time of an estimator tick, outputs included",
                                      buckets=_TICK_BUCKETS, registry=r)
        self.loop_lag_seconds = Histogram("bms_loop_lag_seconds", "lateness of the event loop against its schedule",
                                          buckets=_LAG_BUCKETS, registry=r)
        self.mqtt_publish_latency = Histogram(
            "bms_mqtt_publish_latency_seconds", "time from a state's submission to its publication (acknowledged for QoS > 0)",
            buckets=_PUBLISH_BUCKETS, registry=r)
        self.mqtt_published = Counter("bms_mqtt_published", "MQTT messages published", registry=r)
        self.mqtt_dropped = Counter("bms_mqtt_dropped", "MQTT states never sent (superseded or buffer full)",
                                    registry=r)
        self.mqtt_connects = Counter("bms_mqtt_connects", "successful MQTT connections", registry=r)
        self.mqtt_connect_failures = Counter("bms_mqtt_connect_failures", "failed MQTT connection attempts",
                                             registry=r)
        self.mqtt_connected = Gauge("bms_mqtt_connected", "1 while connected to the MQTT broker", registry=r)
        self.state_saves = Counter("bms_state_saves", "estimator state files written", registry=r)
        self.state_save_errors = Counter("bms_state_save_errors", "estimator state saves that failed", registry=r)
        self.estimator_state.state(EstimatorState.INIT.label)
        self._collector: _ServiceCollector | None = None

    def attach(self, service: Service) -> None:
        """Read the service's components at every scrape."""
        if self._collector is None:
            self._collector = _ServiceCollector(service, self.cell_metrics)
            self.registry.register(self._collector)

    def observe_tick(self, seconds: float) -> None:
        self.tick_seconds.observe(seconds)

    def set_state(self, state: EstimatorState) -> None:
        self.estimator_state.state(state.label)


#: pack SOX figure -> (metric, help); the SOP limits are labelled families below
_SOX_GAUGES = (
    ("energy_left_wh", "bms_pack_energy_left_wh", "energy left to the cut-off at the stated rate"),
    ("energy_delivered_wh", "bms_pack_energy_delivered_wh", "net energy out since the pack was last full"),
    ("energy_discharged_wh", "bms_pack_energy_discharged_wh", "energy discharged since the service first started"),
    ("time_to_empty_s", "bms_pack_time_to_empty_seconds", "time to the cut-off at the recent mean current (+Inf idle)"),
    ("time_to_full_s", "bms_pack_time_to_full_seconds", "time to full at the recent mean current (+Inf idle)"),
)


def _counter(name: str, doc: str, value: float, labels: dict[str, float] | None = None,
             label: str = "") -> CounterMetricFamily:
    if labels is None:
        return CounterMetricFamily(name, doc, value=value)
    fam = CounterMetricFamily(name, doc, labels=[label])
    for key, v in labels.items():
        fam.add_metric([key], v)
    return fam


def _gauge(name: str, doc: str, value: float) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, doc, value=value)


class _ServiceCollector(Collector):
    """Counters owned by the service's components, and the battery figures, at scrape time."""

    def __init__(self, service: Service, cell_metrics: bool) -> None:
        self.svc = service
        self.cell_metrics = cell_metrics

    def describe(self) -> list:
        return []  # values are read at collect time; no registration-time collision check needed

    def collect(self) -> Iterator[Any]:
        svc = self.svc
        dc = svc.decoder.counters if svc.decoder is not None else None
        if dc is not None:
            yield _counter("bms_can_frames_received", "CAN frames received", dc.frames)
            yield _counter("bms_can_frames_decoded", "CAN frames of a mapped message that decoded", dc.decoded)
            yield _counter("bms_can_frames_ignored", "CAN frames ignored", None,
                           {"unknown_id": dc.unknown_id, "unmapped": dc.unmapped, "error_or_remote": dc.ignored},
                           "reason")
            yield _counter("bms_decode_problems", "frames or values rejected while decoding", None,
                           {"short_frame": dc.short_frame, "bad_mux": dc.bad_mux, "decode_error": dc.decode_error,
                            "non_finite": dc.non_finite, "out_of_range": dc.out_of_range,
                            "not_available": dc.not_available, "flagged_invalid": dc.flagged_invalid,
                            "e2e_counter": dc.e2e_counter, "e2e_crc": dc.e2e_crc,
                            "internal_error": dc.internal_error}, "reason")
        sc = svc.sampler.counters
        yield _counter("bms_sample_anomalies", "frames or values the sampler set aside or re-anchored on", None,
                       {"time_jump": sc.time_jumps, "rewind": sc.rewinds, "backward_frame": sc.backward_frames,
                        "bad_timestamp": sc.bad_timestamps, "non_finite_value": sc.non_finite_values,
                        "bad_cell_index": sc.bad_cell_index, "internal_error": sc.internal_errors,
                        "clock_step": svc.pipeline.counters.clock_steps}, "kind")
        yield _counter("bms_cell_samples_stale", "cell inputs stale or missing, summed over samples",
                       sc.stale_cell_samples)
        pc = svc.pipeline.counters
        yield _counter("bms_samples", "samples estimated", pc.samples)
        yield _counter("bms_samples_current_invalid", "samples without a valid current (counted with its running mean, voltages not read)",
                       pc.samples_current_invalid)
        yield _counter("bms_tick_errors", "exceptions while processing a frame, a sample or an output (logged, skipped)",
                       pc.tick_errors)
        yield _counter("bms_estimator_rests", "gaps without samples (time jump, restart) the estimator rested over, "
                       "the pack taken as parked", pc.rests)
        yield _counter("bms_estimator_rest_seconds", "seconds of those gaps", pc.rest_s)
        est = svc.estimator
        yield _counter("bms_estimator_rejections", "identifier updates rejected by the admissibility guard, all cells",
                       int(np.sum(est.identifier.rejections)))
        yield _counter("bms_estimator_corrections", "SOC corrections from the OCV bias, all cells",
                       int(np.sum(est.corrections)))
        yield _counter("bms_estimator_restarts", "identifications restarted after a run of rejections, all cells",
                       int(np.sum(est.identifier.restarts)))
        yield _gauge("bms_state_restored", "1 when the estimator resumed from a saved state", int(svc.restored))
        enc = svc.encoder
        if enc is not None:
            yield _counter("bms_can_encode_problems", "CAN output the encoder could not build", None,
                           {"skipped_cell": enc.skipped_cells, "encode_failure": enc.encode_failures}, "kind")
        bus = svc.bus
        yield _gauge("bms_can_bus_up", "1 while the CAN bus is open", int(bus is not None and bus.is_open))
        if bus is not None:
            bc = bus.counters
            yield _counter("bms_can_bus_events", "CAN bus opens, failed opens, and failures or silences that caused a reopen", None,
                           {"open": bc.opens, "open_failure": bc.open_failures, "error": bc.bus_errors,
                            "silence": bc.silence_reopens}, "event")
            yield _counter("bms_can_rx_dropped", "received CAN frames lost: receive queue full, a datagram that was no CAN "
                           "frame, or dropped by the kernel (socket buffer full; udp_multicast)", None,
                           {"queue_full": bc.rx_dropped, "malformed": bc.rx_malformed,
                            "kernel": bus.refresh_kernel_drops()}, "reason")
            yield _gauge("bms_can_rx_backlog", "frames the receive thread queued that the estimator has not taken yet",
                         bus.rx_backlog)
            yield _counter("bms_can_rx_error_frames", "CAN error frames received", bc.rx_error_frames)
            yield _counter("bms_can_tx_frames", "CAN frames sent", bc.tx_frames)
            yield _counter("bms_can_tx_dropped", "CAN frames not sent (bus down or send queue full)", bc.tx_dropped)
            yield _counter("bms_can_tx_errors", "CAN send errors", bc.tx_errors)
        hb = svc.heartbeat
        age = hb.age_s()
        yield _gauge("bms_heartbeat_age_seconds", "seconds since the last estimator tick (NaN before the first)",
                     math.nan if age is None else age)
        yield _gauge("bms_healthy", "1 while the estimator heartbeat is fresh", int(hb.is_fresh()))
        yield from self._battery(svc)

    @staticmethod
    def _sox(snap: Any) -> Iterator[Any]:
        """SOP limits per direction and horizon, energy, times and SOH (issue 14), when the snapshot has them."""
        sox = snap.pack_sox
        if not sox:
            return
        cur = GaugeMetricFamily("bms_pack_current_limit_amperes", "pack current limit over the horizon (magnitude)",
                                labels=["direction", "horizon"])
        pw = GaugeMetricFamily("bms_pack_power_limit_watts", "pack power limit over the horizon (magnitude)",
                               labels=["direction", "horizon"])
        for key, v in sox.items():
            parts = key.split("_")  # i_discharge_max_10s_a / p_charge_max_2s_w
            if len(parts) == 5 and parts[2] == "max" and parts[0] in ("i", "p"):
                (cur if parts[0] == "i" else pw).add_metric([parts[1], parts[3]], v)
        yield cur
        yield pw
        for key, name, doc in _SOX_GAUGES:
            if key in sox:
                yield _gauge(name, doc, sox[key])
        soh = GaugeMetricFamily("bms_pack_soh_ratio", "state of health of the weakest cell: capacity (estimated / "
                                "stated; NaN until justified) and resistance (R0 at 25 degC / commissioning)",
                                labels=["kind"])
        soh.add_metric(["capacity"], sox.get("soh_capacity_min", math.nan))
        soh.add_metric(["resistance"], sox.get("soh_resistance_max", math.nan))
        yield soh

    def _battery(self, svc: Service) -> Iterator[Any]:
        snap = svc.pipeline.last
        if snap is None:
            return
        yield _gauge("bms_last_sample_time_seconds", "end time of the last sample on the frames' time base", snap.t_s)
        fam = GaugeMetricFamily("bms_pack_soc", "pack SOC over the cells (fraction)", labels=["stat"])
        for stat, v in (("min", snap.soc.soc_min), ("mean", snap.soc.soc_mean), ("max", snap.soc.soc_max)):
            fam.add_metric([stat], v)
        yield fam
        yield _gauge("bms_pack_current_amperes", "pack current, positive = charge (NaN when unknown)", snap.current_a)
        yield _gauge("bms_pack_voltage_volts", "pack voltage (NaN when unknown)", snap.pack_voltage_v)
        yield _gauge("bms_pack_capacity_ah", "mean estimated cell capacity", snap.capacity_ah_mean)
        yield _gauge("bms_cells_stale", "cells whose inputs are stale", snap.n_cells - snap.cells_valid)
        yield _gauge("bms_cells_capacity_at_bound", "cells whose capacity estimate sits at a bound (the stated "
                     "pack.capacity_ah is wrong for them)", snap.cells_capacity_at_bound)
        yield from self._sox(snap)
        if self.cell_metrics:
            cells = [str(i) for i in range(snap.n_cells)]
            if "p_discharge_max_10s_w" in snap.cells:
                fam = GaugeMetricFamily("bms_cell_power_limit_watts", "cell 10 s power limit", labels=["cell", "direction"])
                for d in ("discharge", "charge"):
                    for cell, v in zip(cells, np.asarray(snap.cells[f"p_{d}_max_10s_w"], dtype=float).tolist()):
                        fam.add_metric([cell, d], v)
                yield fam
            for name, doc, key in (("bms_cell_soc", "cell SOC (fraction)", "soc"),
                                   ("bms_cell_r0_ohms", "cell R0", "r0_ohm"),
                                   ("bms_cell_capacity_ah", "cell capacity estimate", "capacity_ah")):
                fam = GaugeMetricFamily(name, doc, labels=["cell"])
                for cell, v in zip(cells, np.asarray(snap.cells[key], dtype=float).tolist()):
                    fam.add_metric([cell], v)
                yield fam
