"""bms-estimator: online 2-RC identification (linear integral filter) and SOC estimation."""

from __future__ import annotations


def package_version() -> str:
    """The installed distribution's version ("0+unknown" when run from a source tree)."""
    try:
        from importlib.metadata import version

        return version("bms-estimator")
    except Exception:  # noqa: BLE001 - not installed
        return "0+unknown"
