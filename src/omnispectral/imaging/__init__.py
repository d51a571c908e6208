"""Imaging core: HDR synthesis (Eqs. (1)-(2)), lens model and calibration (Sec. 4.2), POC registration (Eq. (3))."""

from omnispectral.imaging.blockpoc import block_disparity
from omnispectral.imaging.geometry import CameraModel, Mounting, head_rotation, lonlat_to_ray, ray_to_lonlat
from omnispectral.imaging.hdr import HDRResult, merge_exposures
from omnispectral.imaging.registration import phase_correlate, register_with_fallback
from omnispectral.imaging.response import CameraResponse, recover_response
from omnispectral.imaging.weights import triangle_weight

__all__ = ["CameraModel", "CameraResponse", "HDRResult", "Mounting", "block_disparity", "head_rotation",
           "lonlat_to_ray", "merge_exposures", "phase_correlate", "ray_to_lonlat", "recover_response",
           "register_with_fallback", "triangle_weight"]
