"""aiomqtt's client with socket registrations that survive a socket closed in the meantime.

paho-mqtt tells aiomqtt about its socket from the thread that connects, and aiomqtt
schedules ``loop.add_reader``/``loop.add_writer(sock.fileno(), ...)`` with
``call_soon_threadsafe``. When the connection breaks on a reconnect, paho closes the
socket before the loop runs the scheduled call; asyncio then logs
``Exception in callback BaseSelectorEventLoop.add_writer(...)``,
``OSError: [Errno 9] Bad file descriptor`` at ERROR, for a connection that is already
being re-established. (Had the descriptor number been reused by then, say by the CAN
socket, the callback would have been registered on that.)

:class:`MqttClient` registers only if the socket still has the descriptor it had when
paho reported it, and treats ``OSError`` from the selector as "closed meanwhile".

A connect that does not complete (cancelled while the broker has not answered CONNECT: a
stop, a reload; or refused) left paho's socket open and watched by the loop, with aiomqtt's
keepalive task running, until the keepalive expired; a reset by the peer meanwhile made
aiomqtt's ``on_disconnect`` read the cancelled ``_connected`` future inside a loop callback
(``CancelledError``, "Exception in callback ...": a traceback in the journal).
:meth:`MqttClient.__aenter__` closes the socket of a connect that did not complete.  A cancel
that lands while the TCP connect itself still runs in aiomqtt's executor thread (a broker slow
to accept, a SYN retried) finds no socket yet: the thread then closes the one it made, on the
loop (:meth:`MqttClient._client_connect`); before, that socket stayed open and watched.

A connection the broker drops (a duplicate client id, a broker restart) sets aiomqtt's
``_disconnected`` future to ``MqttCodeError("Unexpected disconnection")``; where no publish or
``__aexit__`` read it before aiomqtt replaced the future (its next ``__aenter__`` does), the garbage
collector logged ``Future exception was never retrieved`` with that traceback at ERROR, about one
dropped connection in 20 (found by the big-pack audit's reconnect churn). The service already logs
and counts the disconnect itself, so every such future has its exception retrieved when it is set
(:attr:`MqttClient._disconnected`); whoever awaits it still gets it.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Any

import aiomqtt

__all__ = ["MqttClient"]


def _retrieve_exception(fut: Any) -> None:
    """Mark a finished future's exception as retrieved (asyncio then never logs it as lost)."""
    if not fut.cancelled():
        fut.exception()


def _register_if_open(add: Callable[[int, Callable[[], None]], None], sock: Any, fd: int,
                      callback: Callable[[], None]) -> None:
    if fd < 0 or sock.fileno() != fd:  # closed (or replaced) before the loop got here
        return
    with contextlib.suppress(OSError):
        add(fd, callback)


class MqttClient(aiomqtt.Client):
    """``aiomqtt.Client`` whose deferred socket registrations are guarded; see the module docstring.

    The two callbacks are aiomqtt 2.x's own (read or write until the socket fails, then
    mark the connection lost), registered through :func:`_register_if_open`."""

    _abandon_guard = threading.Lock()  # the connect thread's check against _abandon (any client: held briefly)
    _abandoned = False

    @property
    def _disconnected(self) -> Any:
        return self.__dict__["_disconnected_future"]

    @_disconnected.setter
    def _disconnected(self, fut: Any) -> None:  # aiomqtt sets it in __init__ and again in __aenter__
        fut.add_done_callback(_retrieve_exception)
        self.__dict__["_disconnected_future"] = fut

    async def __aenter__(self) -> MqttClient:
        with self._abandon_guard:
            self._abandoned = False
        try:
            return await super().__aenter__()
        except BaseException:  # cancelled or refused before it was connected: nothing else closes it
            self._abandon()
            raise

    def _client_connect(self) -> None:
        """aiomqtt's connect, in its executor thread; if the connect was abandoned while it ran (a
        cancel does not stop the thread), the socket it made is closed on the loop."""
        super()._client_connect()
        with self._abandon_guard:
            if not self._abandoned:
                return
        try:
            self._loop.call_soon_threadsafe(self._close_socket)
        except RuntimeError:  # the loop is closed: nothing watches the socket any more
            with contextlib.suppress(Exception):
                self._client._sock_close()  # noqa: SLF001

    def _abandon(self) -> None:
        """Close paho's socket of a connect that did not complete (or have the connect thread close
        it, if it has none yet): its close callback (aiomqtt's) stops watching it and cancels the
        keepalive task; no disconnect callback runs."""
        with self._abandon_guard:
            self._abandoned = True
        self._close_socket()
        if self._lock.locked():
            self._lock.release()

    def _close_socket(self) -> None:
        with contextlib.suppress(Exception):
            self._client._sock_close()  # noqa: SLF001 - paho's own close, without on_disconnect

    def _lost(self, exc: BaseException) -> None:
        if not self._disconnected.done():
            self._disconnected.set_exception(exc)

    def _on_socket_open(self, client: Any, userdata: Any, sock: Any) -> None:
        def on_readable() -> None:
            try:
                while True:
                    client.loop_read()
                    # loop_read() does not always consume the bytes an SSL socket has decoded
                    pending = getattr(client._sock, "pending", None)  # noqa: SLF001
                    if pending is None or pending() <= 0:
                        break
            except Exception as exc:  # noqa: BLE001 - a broken connection: reconnect
                self._lost(exc)

        def create_misc_task() -> None:
            self._misc_task = self._loop.create_task(self._misc_loop())

        self._loop.call_soon_threadsafe(_register_if_open, self._loop.add_reader, sock, sock.fileno(), on_readable)
        self._loop.call_soon_threadsafe(create_misc_task)

    def _on_socket_register_write(self, client: Any, userdata: Any, sock: Any) -> None:
        def on_writable() -> None:
            try:
                client.loop_write()
            except Exception as exc:  # noqa: BLE001
                self._lost(exc)

        self._loop.call_soon_threadsafe(_register_if_open, self._loop.add_writer, sock, sock.fileno(), on_writable)
