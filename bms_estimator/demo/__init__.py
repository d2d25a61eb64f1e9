"""``bms-estimator demo``: a measured drive cycle as the CAN traffic of a pack, through the real service.

``pipeline``  encode a shipped drive cycle for an n-cell pack (seeded spread), feed its frames in
              process into :class:`~bms_estimator.service.daemon.Service` (``Service.feed``: at
              ``max``, or paced by a speed factor), subscribe to its MQTT output and record every
              sample the service estimated
``broker``    the MQTT broker of the demo: the one given, else a Mosquitto started on a free loopback
              port, else an embedded pure-Python broker (amqtt), else none (MQTT off)
``summary``   per-cell SOC error against the reference, voltage RMSE, identified parameters, R0 ranking
              against the injected spread (Spearman), and the figure
``live``      the live terminal view (rich) or plain progress lines

Submodules are imported on use; importing this package loads nothing heavy.
"""
