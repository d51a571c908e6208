"""Mosaic engine: merged directional images → six-band HDR equirectangular panorama (paper Sec. 4.4–4.5).

Public API
----------
:func:`mosaic`                 stitch merged directions into a Zarr panorama store (a raw session is merged
                               first by :func:`omnispectral.product.merge.merge_session`)
:func:`render_tile`            one output tile in memory (the engine's unit of work)
:class:`MergedDirections`      the engine's input on disk; :class:`MergedDirectionsWriter` writes it
:class:`PanoramaStore`         the output store (levels, chunks, markers, metadata)
:func:`polar_image`, :func:`polar_angles_rad`   Eq. (4)
:func:`feather_weight`, :func:`multiband_blend`, :func:`estimate_gains`   blending and gain compensation
"""

from omnispectral.mosaic.blending import feather_weight, multiband_blend
from omnispectral.mosaic.engine import MosaicJob, build_job, mosaic, native_width, render_tile
from omnispectral.mosaic.gain import estimate_gains
from omnispectral.mosaic.interp import METHODS, remap
from omnispectral.mosaic.maps import Canvas, Rect, SourceGeometry, source_map
from omnispectral.mosaic.polar import PolarImage, polar_angles_rad, polar_image, polar_to_image_px
from omnispectral.mosaic.sources import MergedDirections, MergedDirectionsWriter, SourceImage
from omnispectral.mosaic.store import PanoramaStore

__all__ = ["METHODS", "Canvas", "MergedDirections", "MergedDirectionsWriter", "MosaicJob", "PanoramaStore",
           "PolarImage", "Rect", "SourceGeometry", "SourceImage", "build_job", "estimate_gains", "feather_weight",
           "mosaic", "multiband_blend", "native_width", "polar_angles_rad", "polar_image",
           "polar_to_image_px", "remap", "render_tile", "source_map"]
