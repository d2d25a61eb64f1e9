"""End-to-end protection of input frames: an alive (message) counter and a CRC or checksum.

The mapping names them per input message (``[e2e.<message>]``, see
:mod:`bms_estimator.can.mapping`); the decoder drops a frame that fails and counts it
(``e2e_counter``, ``e2e_crc``).

Counter: an unsigned signal of ``L`` bits that the sender increments by one per frame
(per multiplexer value for a multiplexed message), modulo :math:`2^L` (or its DBC maximum
+ 1). A frame is accepted when

.. math:: c_k = (c_{k-1} + 1) \bmod m,

the first frame after start is accepted as the reference. A frame whose counter is not the
next one (a skipped value: a lost or injected frame; a repeated value: a frozen sender) is
dropped, and the counter re-synchronises on it, so one lost frame on the bus costs the frame
after it too and nothing more.

CRC: an 8-bit, byte-aligned signal; the CRC is computed over the frame's other data bytes in
their order (the CRC byte left out) and must equal it. Algorithms (``crc_algorithm``):

* ``crc8_sae_j1850``: polynomial 0x1D, initial value 0xFF, final XOR 0xFF (AUTOSAR E2E profile 1/2's CRC-8);
* ``crc8_autosar``: polynomial 0x2F, initial value 0xFF, final XOR 0xFF (CRC-8H2F);
* ``xor8``: XOR of the bytes; ``sum8``: their sum modulo 256 (simple checksums).
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["CRC_ALGORITHMS", "crc8_autosar", "crc8_sae_j1850", "sum8", "xor8"]


def _crc8_table(poly: int) -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


def _crc8(poly: int, init: int, xorout: int) -> Callable[[bytes], int]:
    table = _crc8_table(poly)

    def crc(data: bytes) -> int:
        c = init
        for b in data:
            c = table[c ^ b]
        return c ^ xorout

    return crc


crc8_sae_j1850 = _crc8(0x1D, 0xFF, 0xFF)
crc8_autosar = _crc8(0x2F, 0xFF, 0xFF)


def xor8(data: bytes) -> int:
    c = 0
    for b in data:
        c ^= b
    return c


def sum8(data: bytes) -> int:
    return sum(data) & 0xFF


#: ``crc_algorithm`` name -> function of the protected bytes
CRC_ALGORITHMS: dict[str, Callable[[bytes], int]] = {
    "crc8_sae_j1850": crc8_sae_j1850,
    "crc8_autosar": crc8_autosar,
    "xor8": xor8,
    "sum8": sum8,
}
