"""Terminal dashboard of the estimator service's MQTT output (``bms-estimator dashboard``).

Subscribes to the service's topics (``<base>`` defaults to ``bms``; topics and payload
keys are defined in ``bms_estimator/service/schema.py``)::

    <base>/<pack>/cell/<i>/state   a cell's state (schema.CELL_FIELDS, "t_s")
    <base>/<pack>/pack/state       the pack's state (schema.PACK_FIELDS)
    <base>/<pack>/availability     online | offline (retained)

and shows, per pack, the availability, the pack summary and a live per-cell table
(SOC, R0, tau1, tau2, c0, the service's stale flag and the AGE of the cell's last
message on this side). Nothing beyond these topics is assumed of the broker.

Testable without a broker: :meth:`DashboardState.apply` takes one message
``(topic, payload, now)``, :func:`render` turns the state into a rich renderable.
Unknown topics and unusable payloads (not UTF-8, not JSON, not an object, an
unknown availability word, an object with none of the keys this version reads: another
schema's) are ignored and counted; a cell payload's field that is not a finite number
counts as missing (``invalid_fields``). The view names the last topics skipped and why
(:attr:`DashboardState.skipped`).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import random
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from rich.console import Group, RenderableType
from rich.table import Table
from rich.text import Text

from .. import aio
from ..service.schema import CELL_KEYS, PACK_FIELDS, PACK_SOX_FIELDS

__all__ = [
    "CellView",
    "DashboardCounters",
    "DashboardState",
    "PackView",
    "render",
    "run_dashboard",
    "parse_broker",
]

#: numeric fields of a cell payload that the dashboard reads
CELL_NUMBERS = tuple(k for k in CELL_KEYS if k != "stale") + ("t_s",)
PACK_NUMBERS = ("t_s", "soc_min", "soc_mean", "soc_max", "current_a", "cells_stale")
#: the pack's SOP/SOE/SOH figures, shown on a line of their own
PACK_SOX_KEYS = tuple(f.key for f in PACK_SOX_FIELDS)
PACK_KEYS = tuple(f.key for f in PACK_FIELDS)
MAX_CELL_INDEX = 100_000  # a larger index in a topic is treated as garbage
SKIPPED_SHOWN = 3  # the last topics skipped that the view names


@dataclass
class CellView:
    values: dict[str, float | None]
    stale: bool | None
    received: float  # `now` of the last message
    messages: int = 1


@dataclass
class PackView:
    pack_id: str
    cells: dict[int, CellView] = field(default_factory=dict)
    summary: dict[str, Any] | None = None
    summary_received: float | None = None
    availability: str | None = None  # "online" / "offline" / None (never seen or cleared)
    availability_received: float | None = None


@dataclass
class DashboardCounters:
    messages: int = 0  # everything apply() saw
    applied: int = 0
    unknown_topic: int = 0  # outside the service's topic layout
    other_pack: int = 0  # a pack the dashboard was told not to show
    invalid_payload: int = 0  # undecodable / wrong type
    invalid_fields: int = 0  # cell/pack fields that were not finite numbers


def _number(x: Any) -> float | None:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    f = float(x)
    return f if math.isfinite(f) else None


def _text(payload: Any) -> str | None:
    if payload is None:
        return ""
    if isinstance(payload, str):
        return payload
    if isinstance(payload, (bytes, bytearray, memoryview)):
        try:
            return bytes(payload).decode("utf-8")
        except UnicodeDecodeError:
            return None
    if isinstance(payload, (int, float)):
        return str(payload)
    return None


class DashboardState:
    """Everything the dashboard knows, fed one MQTT message at a time."""

    def __init__(self, pack_id: str | None = None, base_topic: str = "bms") -> None:
        self.pack_id = pack_id
        self.base_topic = base_topic.strip("/")
        self.packs: dict[str, PackView] = {}
        self.counters = DashboardCounters()
        self.now: float = 0.0
        self.connected: bool = False
        self.ever_connected: bool = False  # the broker was reached at least once
        self.status: str = "not connected"
        self.last_error: str = ""  # why the broker was last out of reach, for the exit message
        self.broker: str = ""
        self.skipped: dict[str, str] = {}  # topic -> why its last message was skipped (or a field), newest last

    # ---------------------------------------------------------------- topics
    def subscriptions(self) -> list[str]:
        pack = self.pack_id if self.pack_id is not None else "+"
        root = f"{self.base_topic}/{pack}"
        return [f"{root}/cell/+/state", f"{root}/pack/state", f"{root}/availability"]

    def tick(self, now: float) -> None:
        """Advance the clock the ages are measured against."""
        self.now = max(self.now, now)

    def _skip(self, counter: str, topic: str, why: str) -> bool:
        """Count a message (or a field) skipped and remember why, for the view; False."""
        setattr(self.counters, counter, getattr(self.counters, counter) + 1)
        self.skipped.pop(topic, None)
        self.skipped[topic] = why
        while len(self.skipped) > 32:
            del self.skipped[next(iter(self.skipped))]
        return False

    def _pack(self, pack_id: str) -> PackView:
        view = self.packs.get(pack_id)
        if view is None:
            view = self.packs[pack_id] = PackView(pack_id)
        return view

    # ----------------------------------------------------------------- apply
    def apply(self, topic: str, payload: Any, now: float) -> bool:
        """Take one message; True if it changed the state. Never raises."""
        c = self.counters
        c.messages += 1
        self.tick(now)
        try:
            return self._apply(str(topic), payload, now)
        except Exception as exc:  # noqa: BLE001 - a dashboard never dies of a message
            return self._skip("invalid_payload", str(topic), f"unusable ({type(exc).__name__})")

    def _apply(self, topic: str, payload: Any, now: float) -> bool:
        c = self.counters
        prefix = self.base_topic + "/"
        layout = "not a topic of the service's layout"
        if not topic.startswith(prefix):
            return self._skip("unknown_topic", topic, layout)
        parts = topic[len(prefix):].split("/")
        if len(parts) < 2 or not parts[0]:
            return self._skip("unknown_topic", topic, layout)
        pack_id, rest = parts[0], parts[1:]
        if rest == ["availability"]:
            kind = "availability"
        elif rest == ["pack", "state"]:
            kind = "pack"
        elif len(rest) == 3 and rest[0] == "cell" and rest[2] == "state":
            kind = "cell"
        else:
            return self._skip("unknown_topic", topic, layout)
        if self.pack_id is not None and pack_id != self.pack_id:
            c.other_pack += 1
            return False
        text = _text(payload)
        if text is None:
            return self._skip("invalid_payload", topic, "not UTF-8 text")
        if kind == "availability":
            word = text.strip().lower()
            if word not in ("online", "offline", ""):
                return self._skip("invalid_payload", topic, f"not online or offline ({_shown(text)!r})")
            view = self._pack(pack_id)
            view.availability = word or None  # empty retained payload = cleared
            view.availability_received = now
            c.applied += 1
            return True
        if kind == "cell":
            idx_text = rest[1]
            if not idx_text.isdigit() or int(idx_text) > MAX_CELL_INDEX:
                return self._skip("unknown_topic", topic, f"cell index {_shown(idx_text)!r} is not 0..{MAX_CELL_INDEX:,}")
        try:
            data = json.loads(text)
        except (ValueError, RecursionError) as exc:
            return self._skip("invalid_payload", topic, f"not JSON ({_shown(str(exc))})")
        if not isinstance(data, dict):
            return self._skip("invalid_payload", topic, f"a JSON {type(data).__name__}, not an object")
        known = CELL_KEYS + ("t_s",) if kind == "cell" else PACK_KEYS
        if data and not any(k in data for k in known):  # another schema's payload (an older service's?)
            return self._skip("invalid_payload", topic, "none of the keys of this version's payload "
                                                        f"(has {_shown(', '.join(map(str, data)))})")
        view = self._pack(pack_id)
        if kind == "cell":
            values: dict[str, float | None] = {}
            for key in CELL_NUMBERS:
                raw = data.get(key)
                values[key] = _number(raw)
                if raw is not None and values[key] is None:
                    self._skip("invalid_fields", topic, f"{key!r} is not a number ({_shown(json.dumps(raw))})")
            for tau, r, cap in (("tau1_s", "r1_ohm", "c1_f"), ("tau2_s", "r2_ohm", "c2_f")):
                if values[tau] is None and values[r] is not None and values[cap] is not None:
                    values[tau] = values[r] * values[cap]
            stale = data.get("stale")
            stale_v = stale if isinstance(stale, bool) else None
            if stale is not None and stale_v is None:
                self._skip("invalid_fields", topic, f"'stale' is not true or false ({_shown(json.dumps(stale))})")
            idx = int(rest[1])
            old = view.cells.get(idx)
            view.cells[idx] = CellView(values, stale_v, now, (old.messages + 1) if old else 1)
        else:
            summary: dict[str, Any] = {}
            for key, raw in data.items():
                if key in PACK_NUMBERS or key in PACK_SOX_KEYS:
                    summary[key] = _number(raw)
                    if raw is not None and summary[key] is None:
                        self._skip("invalid_fields", topic, f"{key!r} is not a number ({_shown(json.dumps(raw))})")
                elif isinstance(raw, (int, float, str, bool)) or raw is None:
                    summary[str(key)] = raw
            view.summary = summary
            view.summary_received = now
        c.applied += 1
        return True

    def apply_many(self, messages: Iterable[tuple[str, Any, float]]) -> int:
        return sum(1 for t, p, n in messages if self.apply(t, p, n))


def _shown(text: str, limit: int = 60) -> str:
    """``text`` cut to ``limit`` characters, for the view."""
    return text if len(text) <= limit else text[:limit] + "..."


# --------------------------------------------------------------------- render
def _fmt(x: float | None, scale: float = 1.0, digits: int = 2) -> str:
    return "-" if x is None else f"{x * scale:.{digits}f}"


def _age(now: float, t: float | None) -> str:
    if t is None:
        return "-"
    a = max(0.0, now - t)
    return f"{a:.1f}" if a < 100 else f"{a:.0f}"


def _cell_table(view: PackView, indices: list[int], now: float, stale_after_s: float) -> Table:
    t = Table(box=None, pad_edge=False, header_style="bold", show_edge=False)
    for name, justify in (("cell", "right"), ("SOC %", "right"), ("R0 mΩ", "right"), ("τ1 s", "right"),
                          ("τ2 s", "right"), ("c0 mV", "right"), ("stale", "center"), ("age s", "right")):
        t.add_column(name, justify=justify, no_wrap=True)
    for i in indices:
        cell = view.cells[i]
        v = cell.values
        age = now - cell.received
        old = age > stale_after_s
        style = "red" if cell.stale else ("yellow" if old else "")
        t.add_row(
            str(i), _fmt(v["soc"], 100, 2), _fmt(v["r0_ohm"], 1e3, 3), _fmt(v["tau1_s"], 1, 1),
            _fmt(v["tau2_s"], 1, 0), _fmt(v["c0_v"], 1e3, 2),
            "-" if cell.stale is None else ("yes" if cell.stale else "no"), _age(now, cell.received),
            style=style,
        )
    return t


def _pack_line(view: PackView, now: float) -> Text:
    txt = Text()
    txt.append(f"pack {view.pack_id}  ", style="bold")
    av = view.availability
    txt.append(av or "availability unknown", style={"online": "bold green", "offline": "bold red"}.get(av or "", "dim"))
    if view.availability_received is not None:
        txt.append(f" ({_age(now, view.availability_received)} s ago)", style="dim")
    s = view.summary
    if s is None:
        txt.append("   no pack state yet", style="dim")
        return txt
    txt.append("   SOC min/mean/max ")
    txt.append(f"{_fmt(s.get('soc_min'), 100)} / {_fmt(s.get('soc_mean'), 100)} / {_fmt(s.get('soc_max'), 100)} %",
               style="bold")
    txt.append(f"   current {_fmt(s.get('current_a'), 1, 3)} A")
    cs = s.get("cells_stale")
    txt.append(f"   stale cells {'-' if cs is None else int(cs)}")
    if s.get("t_s") is not None:
        txt.append(f"   t {s['t_s']:.1f} s")
    txt.append(f"   ({_age(now, view.summary_received)} s ago)", style="dim")
    if s.get("p_discharge_max_10s_w") is not None or s.get("energy_left_wh") is not None:
        txt.append("\n  10 s power limit discharge ")
        txt.append(f"{_fmt(s.get('p_discharge_max_10s_w'), 1e-3, 2)} kW", style="bold")
        txt.append(f" ({_fmt(s.get('i_discharge_max_10s_a'), 1, 1)} A), charge ")
        txt.append(f"{_fmt(s.get('p_charge_max_10s_w'), 1e-3, 2)} kW", style="bold")
        txt.append(f" ({_fmt(s.get('i_charge_max_10s_a'), 1, 1)} A)   energy left {_fmt(s.get('energy_left_wh'), 1, 0)} Wh"
                   f"   to empty {_fmt(s.get('time_to_empty_s'), 1 / 60, 0)} min"
                   f"   SOH capacity {_fmt(s.get('soh_capacity_min'), 100, 1)} %, resistance "
                   f"{_fmt(s.get('soh_resistance_max'), 100, 1)} %")
    extras = [(k, v) for k, v in s.items() if k not in PACK_NUMBERS and k not in PACK_SOX_KEYS]
    if extras:
        txt.append("\n  " + "  ".join(f"{k}={v}" for k, v in extras[:12]), style="dim")
    return txt


def render(state: DashboardState, *, max_rows: int | None = None, stale_after_s: float = 5.0) -> RenderableType:
    """The dashboard as a rich renderable. ``max_rows`` splits a long cell list into side-by-side
    tables; ages are ``state.now`` minus each message's receive time."""
    c = state.counters
    now = state.now
    head = Text()
    head.append("bms-estimator dashboard", style="bold")
    if state.broker:
        head.append(f"  {state.broker}")
    head.append("  connected" if state.connected else f"  {state.status}",
                style="green" if state.connected else "red")
    head.append(f"   messages {c.messages}  ignored: topic {c.unknown_topic}, payload {c.invalid_payload}, "
                f"fields {c.invalid_fields}" + (f", other packs {c.other_pack}" if c.other_pack else ""),
                style="dim")
    parts: list[RenderableType] = [head]
    if state.skipped:
        shown = list(state.skipped.items())[-SKIPPED_SHOWN:]
        parts.append(Text("  skipped: " + "; ".join(f"{t}: {why}" for t, why in reversed(shown)), style="yellow"))
    if not state.packs:
        parts.append(Text("waiting for messages on " + ", ".join(state.subscriptions()), style="dim"))
    for pack_id in sorted(state.packs):
        view = state.packs[pack_id]
        parts.append(_pack_line(view, now))
        idx = sorted(view.cells)
        if not idx:
            parts.append(Text("  no cell states yet", style="dim"))
            continue
        rows = max_rows if max_rows and max_rows > 0 else len(idx)
        chunks = [idx[k : k + rows] for k in range(0, len(idx), rows)]
        if len(chunks) == 1:
            parts.append(_cell_table(view, chunks[0], now, stale_after_s))
        else:
            grid = Table.grid(padding=(0, 3))
            for _ in chunks:
                grid.add_column()
            grid.add_row(*(_cell_table(view, ch, now, stale_after_s) for ch in chunks))
            parts.append(grid)
    return Group(*parts)


# ----------------------------------------------------------------- subscriber
def parse_broker(text: str, default_port: int = 1883) -> tuple[str, int]:
    """``HOST[:PORT]`` (``[v6]:PORT`` for IPv6)."""
    text = text.strip()
    if text.startswith("["):
        host, _, rest = text[1:].partition("]")
        port = rest[1:] if rest.startswith(":") else ""
    elif text.count(":") == 1:
        host, _, port = text.partition(":")
    else:
        host, port = text, ""
    if not host:
        raise ValueError(f"--broker {text!r}: no host")
    try:
        p = int(port) if port else default_port
    except ValueError:
        raise ValueError(f"--broker {text!r}: port {port!r} is not a number") from None
    if not 0 < p < 65536:
        raise ValueError(f"--broker {text!r}: port out of range")
    return host, p


async def run_dashboard(
    state: DashboardState,
    host: str,
    port: int = 1883,
    *,
    username: str | None = None,
    password: str | None = None,
    tls_context: Any = None,
    duration_s: float | None = None,
    stop: asyncio.Event | None = None,
    on_message: Callable[[], None] | None = None,
    reconnect_min_s: float = 0.5,
    reconnect_max_s: float = 10.0,
    clock: Callable[[], float] = time.monotonic,
) -> None:
    """Subscribe and feed ``state`` until ``duration_s`` passed or ``stop`` is set; reconnects
    with back-off while the broker is away (``state.connected``/``state.status`` say so)."""
    import aiomqtt

    state.broker = f"{host}:{port}"
    stop = stop or asyncio.Event()
    timer = None
    if duration_s is not None:
        timer = asyncio.get_running_loop().call_later(duration_s, stop.set)
    delay = reconnect_min_s
    try:
        while not stop.is_set():
            try:
                client = aiomqtt.Client(
                    host, port, username=username, password=password, tls_context=tls_context,
                    identifier=f"bms-dashboard-{os.getpid()}-{random.randrange(1 << 30):x}",
                )
                async with client:
                    for topic in state.subscriptions():
                        await client.subscribe(topic, qos=0)
                    aio.raise_if_cancelling()  # one aiomqtt's subscribe swallowed: never wait on it
                    state.connected, state.status = True, "connected"
                    state.ever_connected = True
                    delay = reconnect_min_s
                    reader = asyncio.ensure_future(_read(client, state, on_message, clock))
                    waiter = asyncio.ensure_future(stop.wait())
                    try:
                        done, _ = await asyncio.wait({reader, waiter}, return_when=asyncio.FIRST_COMPLETED)
                        if reader in done:
                            reader.result()  # re-raise a lost connection
                    finally:
                        for task in (reader, waiter):
                            task.cancel()
                            with contextlib.suppress(BaseException):
                                await task
            except aiomqtt.MqttError as exc:
                state.connected, state.status = False, f"broker unreachable ({exc}); retrying"
                state.last_error = str(exc)
                with contextlib.suppress(asyncio.TimeoutError):
                    await aio.wait_for(stop.wait(), timeout=delay)
                delay = min(delay * 2.0, reconnect_max_s)
            finally:
                state.connected = False
        state.status = "stopped"
    finally:
        if timer is not None:
            timer.cancel()


async def _read(client: Any, state: DashboardState, on_message: Callable[[], None] | None,
                clock: Callable[[], float]) -> None:
    async for message in client.messages:
        state.apply(message.topic.value, message.payload, clock())
        if on_message is not None:
            on_message()
