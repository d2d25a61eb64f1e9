"""Service infrastructure of the daemon (no daemon loop here).

Modules (import them directly; this package imports nothing heavy):

``config``   ``load_config(path) -> ServiceConfig`` (TOML + ``BMS_`` env, strict), ``ConfigError``
``logging``  ``configure_logging(level, fmt)`` - JSON under systemd, console in a terminal
``mqtt``     ``MqttPublisher(cfg.mqtt, pack_id, n_cells, metrics=...)``: ``submit_cells``,
             ``submit_pack``, ``await run()``, ``await close()``; ``pack_summary(...)``
``state``    ``save_state`` / ``try_save_state`` (atomic .npz), ``load_state`` (never raises)
``health``   ``Heartbeat``, ``Metrics``, ``HealthServer`` (/healthz, /metrics)
``systemd``  ``notify_ready/status/stopping/watchdog``, ``watchdog_interval_s``, ``watchdog_loop``

Typical composition (sketch)::

    cfg = load_config(path)
    configure_logging(cfg.logging.level, cfg.logging.format)
    metrics = Metrics()
    hb = Heartbeat(cfg.estimator.sample_period_s, cfg.health.stale_after_periods)
    pub = MqttPublisher(cfg.mqtt, cfg.pack.pack_id, cfg.pack.n_cells, metrics=metrics)
    saved = load_state(cfg.state.path, pack_id=cfg.pack.pack_id,
                       n_cells=cfg.pack.n_cells, max_age_s=cfg.state.max_age_s)
    async with asyncio.TaskGroup() as tg:
        tg.create_task(pub.run())
        if cfg.health.enabled:
            tg.create_task(HealthServer.from_config(cfg.health, hb, metrics).run())
        tg.create_task(systemd.watchdog_loop(hb))
        notify_ready("estimating")
        ...  # every tick: hb.beat(); pub.submit_cells(t, arrays); pub.submit_pack(...)
    # on SIGTERM: notify_stopping(); try_save_state(...); await pub.close(); cancel the rest
"""
