"""Replaying recorded drive cycles as pack CAN traffic, and watching the service's MQTT output.

``encode_log``  a measured single-cell CSV -> the CAN traffic of an n-cell pack (.log/.asc/.blf)
                with a seeded, documented cell-to-cell spread and a truth sidecar JSON
``replay``      a CAN log -> a bus (virtual, socketcan, udp_multicast), paced by the log's own
                timestamps at any speed, log timestamps preserved where the interface allows
``dashboard``   terminal view of the service's MQTT topics (rich Live)
``bench``       replay + decode + sample assembly + SOC estimator speed against real time

Submodules are imported on use (``from bms_estimator.replay.replay import replay_messages``);
importing this package loads nothing heavy.
"""
