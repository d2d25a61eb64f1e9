"""CAN side of the bms-estimator service.

One concept per module:

``dbc``      where the project's DBC is (:func:`project_dbc_path`) and strict loading
``mapping``  which DBC signals carry current, pack voltage, cell voltages/temperatures (presets + loader)
``decoder``  :class:`FrameDecoder`: ``can.Message`` -> list of :class:`Event` (SI units), never raises
``sampler``  :class:`SampleAssembler`: events -> fixed-period :class:`Sample` on FRAME time
``encoder``  :class:`StateEncoder`: estimator state -> ``can.Message`` (clamped, NaN -> NotAvailable)
``bus``      :class:`ResilientBus`: python-can bus for asyncio that reopens itself

The service's data path, hop by hop, is in the docstring of :mod:`bms_estimator.service.pipeline`.
"""

from .bus import BusConfig, BusCounters, ResilientBus, open_bus
from .dbc import load_db, load_project_db, project_dbc_path
from .decoder import DecodeCounters, Event, EventKind, FrameDecoder, MappedSignal
from .encoder import StateEncoder
from .mapping import CanMapping, MappingError, load_mapping, mapping_to_dict, preset_names, preset_path
from .sampler import Sample, SampleAssembler, SamplerCounters

__all__ = [
    "BusConfig",
    "BusCounters",
    "CanMapping",
    "DecodeCounters",
    "Event",
    "EventKind",
    "FrameDecoder",
    "MappedSignal",
    "MappingError",
    "ResilientBus",
    "Sample",
    "SampleAssembler",
    "SamplerCounters",
    "StateEncoder",
    "load_db",
    "load_mapping",
    "load_project_db",
    "mapping_to_dict",
    "open_bus",
    "preset_names",
    "preset_path",
    "project_dbc_path",
]
