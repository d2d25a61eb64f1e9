"""The identification methods by name: :func:`make_identifier` builds the one ``IdentifierConfig.method`` names.

The methods (``METHODS``): ``lif`` (continuous time, RLS: :class:`~bms_estimator.core.identifier.LifEstimator`),
``lif-iv`` (continuous time, recursive IV: ``core/lif_iv.py``), ``lif-iv-bv`` (with a kinetic term:
``core/lif_bv.py``), ``lif-iv-ct`` (with a charge-transfer fast branch: ``core/lif_ct.py``) and ``arx`` (the
paper's discrete-time baseline: :class:`~bms_estimator.core.identifier.ArxEstimator`).  The IV variants
subclass ``LifEstimator``; this module sits above them all, so none imports another in a circle.
"""

from __future__ import annotations

from .identifier import METHODS, ArxEstimator, Identifier, IdentifierConfig, LifEstimator
from .lif_bv import LifIvBvEstimator
from .lif_ct import LifIvCtEstimator
from .lif_iv import LifIvEstimator

__all__ = ["make_identifier"]

_BY_METHOD: dict[str, type[Identifier]] = {
    "lif": LifEstimator,
    "lif-iv": LifIvEstimator,
    "lif-iv-bv": LifIvBvEstimator,
    "lif-iv-ct": LifIvCtEstimator,
    "arx": ArxEstimator,
}
assert set(_BY_METHOD) == set(METHODS)


def make_identifier(n_cells: int, dt_s: float, capacity_ah, config: IdentifierConfig = IdentifierConfig()) -> Identifier:
    """The identifier ``config.method`` names, for ``n_cells`` cells sampled every ``dt_s`` seconds."""
    cls = _BY_METHOD.get(config.method)
    if cls is None:
        raise ValueError(f"unknown identification method {config.method!r}: use {', '.join(map(repr, METHODS))}")
    return cls(n_cells, dt_s, capacity_ah, config)
