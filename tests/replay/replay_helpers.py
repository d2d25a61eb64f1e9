"""Constants shared by the replay tests (imported by module name); the broker is service_helpers's."""

from __future__ import annotations


from service_helpers import MOSQUITTO, Broker, free_port, mosquitto_available  # noqa: F401 - re-exported

#: the shared encoded log: first 600 s of the shipped Panasonic cycle_1, 8 cells
CELL, CYCLE, N_CELLS, DURATION_S, SEED = "panasonic-18650pf", "cycle_1", 8, 600, 7
