"""The demo's view of the running pack: rich Live on a terminal, plain progress lines otherwise.

Both are ``on_tick`` callbacks of :func:`~bms_estimator.demo.pipeline.run_pipeline` (called
from its event loop every 0.25 s of wall time). The table is
:func:`bms_estimator.replay.dashboard.render` of the dashboard state that the MQTT subscriber
feeds (or the service directly when there is no broker), under a progress line.
"""

from __future__ import annotations

import math
import time
from typing import Any, TextIO

import numpy as np

__all__ = ["LiveView", "PlainView", "progress_text"]


def progress_text(view: Any) -> str:
    svc, p = view.svc, view.progress
    last = svc.pipeline.last
    t_log = last.t_s if last is not None else math.nan
    t_log = 0.0 if not math.isfinite(t_log) else t_log
    el = p.elapsed()
    pct = 100.0 * t_log / p.log_total_s if p.log_total_s > 0 else 0.0
    rate = t_log / el if el > 0 else 0.0
    speed = "max" if math.isinf(p.speed) else f"{p.speed:g}x"
    return (f"replay {t_log:,.0f}/{p.log_total_s:,.0f} s of log ({pct:3.0f} %)  {rate:5.0f}x real time "
            f"(speed {speed})  {svc.pipeline.counters.samples:,} samples  {svc.decoder.counters.frames:,} frames  "
            f"{el:5.1f} s")


class LiveView:
    """rich Live: progress line + the dashboard's cell tables."""

    def __init__(self, console: Any = None, max_rows: int = 8, title: str = "") -> None:
        from rich.console import Console
        from rich.live import Live

        self.console = console or Console()
        self.max_rows = max_rows
        self.title = title
        self.live = Live(console=self.console, auto_refresh=False, transient=False, redirect_stderr=False)
        self._started = False

    def __enter__(self) -> "LiveView":
        self.live.start()
        self._started = True
        return self

    def __exit__(self, *exc: object) -> None:
        if self._started:
            self.live.stop()
            self._started = False

    def __call__(self, view: Any) -> None:
        from rich.console import Group
        from rich.text import Text

        from ..replay.dashboard import render

        with view.lock:
            table = render(view.state, max_rows=self.max_rows, stale_after_s=30.0)
        parts = []
        if self.title:
            parts.append(Text(self.title, style="bold"))
        parts.append(Text(progress_text(view), style="cyan"))
        parts.append(table)
        self.live.update(Group(*parts), refresh=True)


class PlainView:
    """One line every ``every_s`` seconds of wall time (and at the end) for logs and pipes."""

    def __init__(self, stream: TextIO, every_s: float = 5.0) -> None:
        self.stream = stream
        self.every_s = every_s
        self._next = time.perf_counter() + 1.0

    def __enter__(self) -> "PlainView":
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def __call__(self, view: Any, force: bool = False) -> None:
        now = time.perf_counter()
        if now < self._next and not force:
            return
        self._next = now + self.every_s
        est = view.svc.estimator
        soc = est.soc[np.isfinite(est.soc)]
        r0 = est.params["r0_ohm"]
        with view.lock:
            msgs = view.state.counters.messages
            connected = view.state.connected
            over_mqtt = bool(view.state.broker)
        soc_txt = (f"SOC min/mean/max {100 * soc.min():.1f}/{100 * soc.mean():.1f}/{100 * soc.max():.1f} %"
                   if soc.size else "SOC -")
        if over_mqtt:
            mqtt = f"MQTT {msgs:,} messages received" + (" (connected)" if connected else " (not connected)")
        else:
            mqtt = "MQTT off"
        print(f"  {progress_text(view)}  {soc_txt}  R0 mean {1e3 * float(np.nanmean(r0)):.2f} mOhm  {mqtt}",
              file=self.stream, flush=True)
