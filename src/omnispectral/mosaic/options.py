"""How a mosaic is made: :class:`MosaicOptions`, every choice of :func:`omnispectral.mosaic.engine.mosaic` in one
frozen object, validated once when it is built.

The choices name their methods by the keys of the METHODS-style tables of the modules that implement them:
interpolation :data:`omnispectral.mosaic.interp.METHODS` (paper Sec. 4.4: the one resampling per output pixel),
blending :data:`omnispectral.mosaic.blending.BLENDS` (paper Sec. 4.5: linear blending; or multi-band, Burt &
Adelson 1983).  Sizes are in pixels of the equirectangular panorama (width ``W``, height ``W / 2``).
"""

from __future__ import annotations

from dataclasses import dataclass

from omnispectral.choices import DEFAULT_TILE, options_or_keywords
from omnispectral.errors import ConfigurationError
from omnispectral.mosaic.blending import DEFAULT_MULTIBAND_LEVELS, blend_method
from omnispectral.mosaic.interp import interpolation
from omnispectral.spectral.conditional import BandPredictor

__all__ = ["DEFAULT_INTERP", "DEFAULT_TILE", "MAX_TILE_PX", "MIN_TILE_PX", "MIN_WIDTH_PX", "MosaicOptions"]

#: Interpolation of :func:`~omnispectral.mosaic.engine.mosaic` called as a library function (``process`` and the
#: ``mosaic`` command choose ``cubic-clamped``, :data:`omnispectral.product.process.DEFAULT_INTERP`).
DEFAULT_INTERP = "spline"
#: Smallest tile side, px.
MIN_TILE_PX = 16
#: Largest tile side, px: a tile's maps, weights and six bands in float32 stay within a few GiB.
MAX_TILE_PX = 8192
#: Smallest panorama width, px.
MIN_WIDTH_PX = 8


@dataclass(frozen=True)
class MosaicOptions:
    """Every choice of a mosaic run (validated in ``__post_init__``; unknown method names list the valid ones).

    Attributes
    ----------
    width
        Panorama width in px (height = width / 2), an even number ≥ 8; ``None``: the native width of camera A
        (:func:`omnispectral.imaging.geometry.native_width`).
    tile
        Tile (and chunk) side in px, from :data:`MIN_TILE_PX` to :data:`MAX_TILE_PX`.
    interp
        Interpolation, a key of :data:`omnispectral.mosaic.interp.METHODS`.
    blend
        Blending, a key of :data:`omnispectral.mosaic.blending.BLENDS`.
    multiband_levels
        Pyramid levels of multi-band blending.
    gain_compensation
        Equalise per-direction gains in the overlaps (:mod:`omnispectral.mosaic.gain`).
    scheduler, workers
        ``None`` for Dask's local threaded scheduler with ``workers`` threads (default: all cores), or a Dask
        distributed scheduler address / ``Client``.
    overwrite
        Replace an existing store instead of resuming it.
    compression
        Chunk compression of the store (:class:`omnispectral.mosaic.store.PanoramaStore`).
    region
        ``(row0, row1, col0, col1)`` px of level 0: compute only the tiles meeting this window.
    b_predictor
        The prior's predictor of camera B's bands from A's, used where B saw nothing
        (:mod:`omnispectral.mosaic.predict`); ``None`` fits one per tile.
    edge_model
        Give output pixels at straight edges their footprint's share of each side (the partial-area edge model,
        :mod:`omnispectral.mosaic.edges`) instead of the interpolated value alone.
    """

    width: int | None = None
    tile: int = DEFAULT_TILE
    interp: str = DEFAULT_INTERP
    blend: str = "linear"
    multiband_levels: int = DEFAULT_MULTIBAND_LEVELS
    gain_compensation: bool = False
    scheduler: object = None
    workers: int | None = None
    overwrite: bool = False
    compression: str = "blosc-zstd"
    region: tuple[int, int, int, int] | None = None
    b_predictor: BandPredictor | None = None
    edge_model: bool = True

    def __post_init__(self):
        interpolation(self.interp)
        blend_method(self.blend)
        if self.tile < MIN_TILE_PX:
            raise ConfigurationError(f"tile must be at least {MIN_TILE_PX} px, got {self.tile}")
        if self.tile > MAX_TILE_PX:
            raise ConfigurationError(f"tile must be at most {MAX_TILE_PX} px, got {self.tile}")
        if self.width is not None:
            width = int(self.width)
            if width < MIN_WIDTH_PX or width % 2:
                raise ConfigurationError(f"width must be an even number ≥ {MIN_WIDTH_PX}, got {width}")
            object.__setattr__(self, "width", width)
        if self.workers is not None and (isinstance(self.workers, bool) or int(self.workers) < 1):
            raise ConfigurationError(f"workers must be at least 1 (or None: every core), got {self.workers}")

    @classmethod
    def from_keywords(cls, options: MosaicOptions | None = None, **keywords) -> MosaicOptions:
        """``options``, or the options the keywords of :func:`~omnispectral.mosaic.engine.mosaic` describe.

        Parameters
        ----------
        options
            Options built by the caller, or ``None``.
        **keywords
            The entry point's keywords (one per field).  With ``options`` given, each must be left at its
            default: the two ways of choosing do not mix.

        Returns
        -------
        MosaicOptions
            The validated options.
        """
        return options_or_keywords(cls, options, keywords)
