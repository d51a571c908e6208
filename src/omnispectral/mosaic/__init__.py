"""Mosaic engine: merged directional images → six-band HDR equirectangular panorama (paper Sec. 4.4–4.5).

Public API
----------
:func:`mosaic`                 stitch merged directions into a Zarr panorama store (a raw session is merged
                               first by :func:`omnispectral.product.merge.merge_session`); its choices are one
                               :class:`MosaicOptions`
:func:`render_tile`            one output tile in memory (the unit of work, :mod:`omnispectral.mosaic.tile`)
:class:`MergedDirections`      the engine's input on disk; :class:`MergedDirectionsWriter` writes it
:class:`PanoramaStore`         the output store (levels, chunks, markers, metadata)
:func:`polar_image`, :func:`polar_angles_rad`   Eq. (4)
:func:`feather_weight`, :func:`multiband_blend`, :func:`estimate_gains`   blending and gain compensation

Modules
-------
``engine``     the entry point :func:`mosaic` (options → job → store → tiles → pyramid → summary)
``options``    :class:`MosaicOptions`, the run's choices, validated once
``tile``       one tile: :class:`MosaicJob`, :func:`build_job`, resampling of each source, blending
               (``TILE_RENDERERS`` by blend name), :func:`render_tile`, the tile and pyramid tasks
``run``        running the tasks on Dask (``run_tasks``), level 0 and the pyramid, resuming
``metadata``   the store's attributes, the run's fingerprint, the summary
``maps``, ``interp`` (``METHODS``), ``blending`` (``BLENDS``), ``predict``, ``gain``, ``kernels``, ``sources``,
``store``, ``polar``, ``cluster``   the building blocks
"""

from omnispectral.imaging.geometry import native_width
from omnispectral.mosaic.blending import feather_weight, multiband_blend
from omnispectral.mosaic.engine import mosaic
from omnispectral.mosaic.gain import estimate_gains
from omnispectral.mosaic.interp import METHODS, remap
from omnispectral.mosaic.maps import Canvas, Rect, SourceGeometry, source_map
from omnispectral.mosaic.options import MosaicOptions
from omnispectral.mosaic.polar import PolarImage, polar_angles_rad, polar_image, polar_to_image_px
from omnispectral.mosaic.sources import MergedDirections, MergedDirectionsWriter, SourceImage
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.mosaic.tile import MosaicJob, build_job, render_tile

__all__ = ["METHODS", "Canvas", "MergedDirections", "MergedDirectionsWriter", "MosaicJob", "MosaicOptions",
           "PanoramaStore",
           "PolarImage", "Rect", "SourceGeometry", "SourceImage", "build_job", "estimate_gains", "feather_weight",
           "mosaic", "multiband_blend", "native_width", "polar_angles_rad", "polar_image",
           "polar_to_image_px", "remap", "render_tile", "source_map"]
