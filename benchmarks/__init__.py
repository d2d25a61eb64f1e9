"""Speed benchmarks of bms-estimator: figures, printed by ``bms-estimator bench`` from a source
checkout (they are not part of the installed package), never asserted by the tests.

``can_frames``       CAN decode + sample assembly, frames/s
``publish_latency``  frame that closes a sample -> its MQTT message, through a real Mosquitto
``replay_speedup``   a recorded drive cycle through replay + the service at full speed
``diagnose_speed``   ``diagnose`` on the 4.4 h LG UDDS sample

The estimator figures (cell updates/s, tick time) are in ``bms_estimator/cli/bench.py``.
"""
