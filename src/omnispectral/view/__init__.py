"""The 360° spectral viewer: equirectangular tiles tone-mapped on demand from a product's pyramid, spectra on click.

- :mod:`omnispectral.view.tiles`: :class:`~omnispectral.view.tiles.SlotRenderer` renders any window of the
  equirectangular panorama at any size from the Zarr level that fits (display modes: colour under the
  captured light, one band, spectral uncertainty) and :class:`~omnispectral.view.tiles.TileCache` keeps the
  encoded tiles (LRU, bounded in bytes);
- :mod:`omnispectral.view.server`: the read-only Starlette application (tiles, spectra, probe CSV, the
  vendored Photo Sphere Viewer front end) and :func:`~omnispectral.view.server.serve` (uvicorn).
"""
