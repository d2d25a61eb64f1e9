"""The estimator service (``bms-estimator run``).

The data path is :mod:`~bms_estimator.service.pipeline` (its docstring names each hop);
what leaves the service is defined in :mod:`~bms_estimator.service.schema`.

``config``    ``load_config(path) -> ServiceConfig`` (TOML + systemd credentials + ``BMS_`` env, strict)
``pipeline``  ``Pipeline``: frame -> sample -> estimate -> ``Snapshot``, ``on_snapshot`` hooks, no I/O
``schema``    topics, payload keys, Home Assistant entities, CAN status signals; payload builders
``mqtt``      ``MqttPublisher``: ``submit_snapshot``, ``await run()``, ``await close()``
``metrics``   ``ServiceMetrics``: the Prometheus registry (prometheus_client)
``health``    ``Heartbeat``, ``HealthServer`` (/healthz, /metrics)
``state``     ``save_state`` (atomic .npz), ``load_state`` (never raises)
``systemd``   ``notify_ready/status/stopping/watchdog``, ``watchdog_loop``
``logging``   ``configure_logging(level, fmt)`` - JSON under systemd, console in a terminal
``daemon``    ``Service``: the lifecycle, the bus, state saves, the no-input monitor

This package imports nothing heavy; import the modules directly.
"""
