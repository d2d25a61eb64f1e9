"""The ``udp_multicast`` receiver the service opens: python-can's bus, hardened.

python-can's :class:`~can.interfaces.udp_multicast.UdpMulticastBus` raises
``CanOperationError("could not unpack received message")`` for one malformed
datagram, and a receiver that treats receive errors as a dead bus tears it down
and loses every frame until it has reopened.  :class:`UdpMulticastReceiver`
instead counts the datagram (``malformed``, and the ``on_malformed`` callback
the service's :class:`~bms_estimator.can.bus.ResilientBus` sets) and reads on.

It also

* sets ``SO_RCVBUF`` (``receive_buffer_bytes``, default 4 MiB; the kernel caps
  it at ``net.core.rmem_max``): bursts beyond the socket buffer are lost in the
  kernel, where nothing counts them;
* reports what the kernel dropped: :meth:`UdpMulticastReceiver.kernel_drops`
  reads the socket's ``drops`` from ``/proc/net/udp`` (datagrams that found the
  socket buffer full), so a receiver that falls behind loses nothing uncounted;
* keeps the SENDER's timestamp with ``log_time=True`` (the log time on a
  replay) instead of the socket's receive time.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from typing import Any

import can

try:  # the multicast interface needs msgpack (python-can[multicast])
    from can.interfaces.udp_multicast import UdpMulticastBus as _UdpMulticastBus
    from can.interfaces.udp_multicast.utils import unpack_message as _unpack_message
except ImportError:  # pragma: no cover
    _UdpMulticastBus = None  # type: ignore[assignment,misc]

__all__ = ["UdpMulticastReceiver", "DEFAULT_RECEIVE_BUFFER_BYTES", "udp_socket_drops"]

DEFAULT_RECEIVE_BUFFER_BYTES = 4 << 20


def udp_socket_drops(sock: socket.socket) -> int | None:
    """Datagrams the kernel dropped for this UDP socket (buffer full), from ``/proc/net/udp{,6}``;
    None where that is not available (not Linux, socket closed)."""
    try:
        inode = str(os.fstat(sock.fileno()).st_ino)
    except (OSError, ValueError):
        return None
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            with open(table, encoding="ascii") as fh:
                next(fh, None)  # header
                for line in fh:
                    cols = line.split()
                    # sl local rem st tx:rx tr:when retrnsmt uid timeout inode ref pointer drops
                    if len(cols) >= 13 and cols[9] == inode:
                        return int(cols[12])
        except (OSError, ValueError):
            continue
    return None


if _UdpMulticastBus is not None:

    class UdpMulticastReceiver(_UdpMulticastBus):  # type: ignore[misc,valid-type]
        """``UdpMulticastBus`` that skips and counts malformed datagrams; see the module docstring.

        Same arguments as ``UdpMulticastBus``, plus ``log_time`` and ``receive_buffer_bytes``.
        """

        def __init__(self, *args: Any, log_time: bool = False,
                     receive_buffer_bytes: int | None = DEFAULT_RECEIVE_BUFFER_BYTES, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.log_time = bool(log_time)
            self.malformed = 0
            self.on_malformed: Callable[[], None] | None = None
            self.receive_buffer_bytes: int | None = None
            sock = getattr(self._multicast, "_socket", None)
            if receive_buffer_bytes and sock is not None:
                try:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, int(receive_buffer_bytes))
                    # Linux reports twice the value it grants (its bookkeeping overhead)
                    self.receive_buffer_bytes = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
                except OSError:  # pragma: no cover - best effort
                    pass

        def kernel_drops(self) -> int | None:
            """Datagrams the kernel dropped on this socket since it was opened (None: unknown)."""
            sock = getattr(self._multicast, "_socket", None)
            return None if sock is None else udp_socket_drops(sock)

        def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
            result = self._multicast.recv(timeout)
            if not result:
                return None, False
            data, _sender, rx_time = result
            try:
                msg = _unpack_message(data, replace=None if self.log_time else {"timestamp": rx_time}, check=True)
            except Exception:  # noqa: BLE001 - any undecodable datagram: one frame lost, counted
                self.malformed += 1
                if self.on_malformed is not None:
                    self.on_malformed()
                return None, False
            if self.log_time and not isinstance(msg.timestamp, (int, float)):
                msg.timestamp = rx_time
            if msg.is_fd and getattr(self, "_can_protocol", None) is not can.CanProtocol.CAN_FD:
                return None, False
            return msg, False

else:  # pragma: no cover
    UdpMulticastReceiver = None  # type: ignore[assignment,misc]
