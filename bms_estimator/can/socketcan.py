"""The ``socketcan`` receiver the service opens: python-can's bus, with the kernel's drop count.

A CAN_RAW socket whose receive queue is full loses frames in the kernel. With the
socket option ``SO_RXQ_OVFL`` set, the kernel attaches the socket's cumulative drop
count to every frame it delivers after a drop (an ``SOL_SOCKET``/``SO_RXQ_OVFL``
control message, a ``uint32``). :class:`SocketcanReceiver` sets the option, keeps the
newest count (:meth:`SocketcanReceiver.kernel_drops`, exported by the service as
``bms_can_rx_dropped{reason="kernel"}``) and hands everything else to python-can's own
frame parsing unchanged (:func:`can.interfaces.socketcan.socketcan.capture_message`
reads the socket through :class:`_OverflowTap`). It also sets ``SO_RCVBUF``
(``receive_buffer_bytes``, default 4 MiB, capped by the kernel at ``net.core.rmem_max``) so a
burst waits in the kernel rather than being dropped there.
"""

from __future__ import annotations

import select
import socket
import struct
from typing import Any

import can

from .udp import DEFAULT_RECEIVE_BUFFER_BYTES

__all__ = ["SO_RXQ_OVFL", "SocketcanReceiver", "rxq_overflow_count"]

#: Linux ``SO_RXQ_OVFL`` (asm-generic/socket.h); Python's socket module does not name it
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
_OVFL_SPACE = socket.CMSG_SPACE(4)


def rxq_overflow_count(ancillary: list[tuple[int, int, bytes]]) -> tuple[int | None, list[tuple[int, int, bytes]]]:
    """Split ``recvmsg``'s control messages into the ``SO_RXQ_OVFL`` drop count (None when absent:
    nothing dropped since the socket opened) and the others, in their order."""
    drops = None
    rest = []
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(data) >= 4:
            drops = struct.unpack("=I", data[:4])[0]
        else:
            rest.append((level, kind, data))
    return drops, rest


class _OverflowTap:
    """A socket stand-in for python-can's ``capture_message``: asks for room for the overflow
    control message too, records it, and passes the rest on."""

    __slots__ = ("sock", "drops")

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.drops = 0

    def recvmsg(self, bufsize: int, ancbufsize: int = 0, flags: int = 0) -> tuple[bytes, list, int, Any]:
        data, ancillary, msg_flags, addr = self.sock.recvmsg(bufsize, ancbufsize + _OVFL_SPACE, flags)
        drops, rest = rxq_overflow_count(ancillary)
        if drops is not None:
            self.drops = max(self.drops, drops)
        return data, rest, msg_flags, addr


try:
    from can.interfaces.socketcan.socketcan import SocketcanBus as _SocketcanBus
    from can.interfaces.socketcan.socketcan import capture_message as _capture_message
except ImportError:  # pragma: no cover - not Linux
    _SocketcanBus = None  # type: ignore[assignment,misc]


if _SocketcanBus is not None:

    class SocketcanReceiver(_SocketcanBus):  # type: ignore[misc,valid-type]
        """``SocketcanBus`` that reads ``SO_RXQ_OVFL``; see the module docstring. Same arguments,
        plus ``receive_buffer_bytes``."""

        def __init__(self, *args: Any, receive_buffer_bytes: int | None = DEFAULT_RECEIVE_BUFFER_BYTES,
                     **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.receive_buffer_bytes: int | None = None
            if receive_buffer_bytes:
                try:
                    self.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, int(receive_buffer_bytes))
                    self.receive_buffer_bytes = self.socket.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
                except OSError:  # pragma: no cover - best effort
                    pass
            self.rxq_overflow_enabled = False
            try:
                self.socket.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
                self.rxq_overflow_enabled = True
            except OSError:  # pragma: no cover - a kernel without it: drops stay unknown
                pass
            self._tap = _OverflowTap(self.socket)

        def kernel_drops(self) -> int | None:
            """Frames the kernel dropped on this socket since it was opened (None: not reported)."""
            return self._tap.drops if self.rxq_overflow_enabled else None

        def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
            try:
                ready, _, _ = select.select([self.socket], [], [], timeout)
            except OSError as error:  # the interface went down
                raise can.CanOperationError(f"Failed to receive: {error.strerror}", error.errno) from error
            if not ready:
                return None, self._is_filtered
            msg = _capture_message(self._tap, self.channel == "")  # type: ignore[arg-type]
            if msg and not msg.channel and self.channel:
                msg.channel = self.channel
            return msg, self._is_filtered

else:  # pragma: no cover
    SocketcanReceiver = None  # type: ignore[assignment,misc]
