"""Imaging core: HDR synthesis (Eqs. (1)-(2)); lens model and registration follow."""

from omnispectral.imaging.hdr import HDRResult, merge_exposures, triangle_weight

__all__ = ["HDRResult", "merge_exposures", "triangle_weight"]
