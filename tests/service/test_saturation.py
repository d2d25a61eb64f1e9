"""The real service at a saturated bus (issue 16): nothing is lost without being counted.

``bms-estimator run`` as its own process, 200 cells, CAN output and MQTT on (a Mosquitto,
where installed), reading udp_multicast in a network namespace made for the test, fed
about 7,500 frames/s (every cell voltage every 9 ms: a saturated 1 Mbit/s bus). At the end
``/metrics`` must account for every frame sent: received by the service, or counted as
dropped (receive queue, malformed, kernel socket buffer). Runs benchmarks/saturation.py,
which ``bms-estimator bench --figures saturation_loss_pct`` reports.
"""

from __future__ import annotations

import pytest

from benchmarks.saturation import SaturationResult, bench_saturation

pytest.importorskip("msgpack", reason="udp_multicast needs msgpack (python-can[multicast])")


def _run(**kw) -> SaturationResult:
    res = bench_saturation(n_cells=200, **kw)
    if isinstance(res, str):
        if res.startswith(("no 'ip' command", "cannot create a network namespace", "netns:")):
            pytest.skip(f"netns unavailable: {res}")
        pytest.fail(res)
    return res


def test_saturated_bus_loses_nothing_uncounted():
    res = _run(seconds=8.0)
    assert res.sent > 0.9 * 8.0 * 7_400  # the sender kept the bus saturated
    assert res.samples >= 5  # the service estimated throughout
    assert res.received <= res.sent
    assert res.uncounted == 0, res  # received + counted drops == sent
    if not any(res.counted_lost.values()):
        assert res.received == res.sent


def test_a_receiver_that_falls_behind_counts_what_the_kernel_drops():
    """A socket buffer far too small for the bus (64 KiB): frames are lost, and every one is counted."""
    res = _run(seconds=4.0, receive_buffer_bytes=65_536)
    assert res.uncounted == 0, res
    assert res.received + sum(res.counted_lost.values()) >= res.sent
