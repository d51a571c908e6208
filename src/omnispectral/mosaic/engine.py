"""The mosaic's entry point: merged directional images → multiband equirectangular panorama (paper Sec. 4.4–4.5).

:func:`mosaic` opens the merged directions (:mod:`omnispectral.mosaic.sources`), builds the job every tile
shares (:func:`omnispectral.mosaic.tile.build_job`: one composed map per output pixel and source, one
interpolation, linear blending), creates or resumes the panorama store (:mod:`omnispectral.mosaic.store`, with
the metadata and fingerprint of :mod:`omnispectral.mosaic.metadata`), runs the level-0 tiles and then the
pyramid on Dask (:mod:`omnispectral.mosaic.run`) and returns the run's summary.  Every choice of the run is
one :class:`~omnispectral.mosaic.options.MosaicOptions`, built from the keywords or given as ``options``.
"""

from __future__ import annotations

import time
from pathlib import Path

from omnispectral.errors import InputFileError
from omnispectral.locking import directory_lock
from omnispectral.mosaic.blending import DEFAULT_MULTIBAND_LEVELS, blend_method
from omnispectral.mosaic.gain import estimate_gains
from omnispectral.mosaic.metadata import fingerprint, panorama_attributes, summarise
from omnispectral.mosaic.options import DEFAULT_INTERP, DEFAULT_TILE, MosaicOptions
from omnispectral.mosaic.run import run_level0, run_pyramid, tiles_in
from omnispectral.mosaic.sources import MergedDirections
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.mosaic.tile import N_QUALITY, build_job
from omnispectral.progress import ProgressCallback, optional_progress
from omnispectral.spectral.conditional import BandPredictor

__all__ = ["mosaic", "open_input"]


def open_input(source: str | Path | MergedDirections) -> MergedDirections:
    """Merged directions, open or as a directory; a raw session must be merged first
    (:func:`omnispectral.product.merge.merge_session`, which the ``mosaic`` command runs).

    Parameters
    ----------
    source
        Merged directions, or their directory (``merged.json``).

    Returns
    -------
    MergedDirections
        The merged directions, open.

    Raises
    ------
    InputFileError
        For a capture session or a directory that holds neither.
    """
    if isinstance(source, MergedDirections):
        return source
    path = Path(source)
    if (path / "merged.json").is_file():
        return MergedDirections.open(path)
    if (path / "session.json").is_file():
        raise InputFileError(path, "a capture session: merge it into directions first "
                                   "(omnispectral.product.merge.merge_session, or the 'mosaic' command)")
    raise InputFileError(path, "neither a capture session (session.json) nor merged directions (merged.json)")


def mosaic(source: str | Path | MergedDirections, output: str | Path, *, options: MosaicOptions | None = None,
           width: int | None = None, tile: int = DEFAULT_TILE, interp: str = DEFAULT_INTERP, blend: str = "linear",
           multiband_levels: int = DEFAULT_MULTIBAND_LEVELS, gain_compensation: bool = False,
           scheduler=None, workers: int | None = None, overwrite: bool = False, compression: str = "blosc-zstd",
           region: tuple[int, int, int, int] | None = None, b_predictor: BandPredictor | None = None,
           edge_model: bool = True, progress: ProgressCallback | None = None) -> dict:
    """Stitch a six-band panorama into a Zarr store; returns a summary (see
    :func:`omnispectral.mosaic.metadata.summarise`).

    Parameters
    ----------
    source
        Merged directions (:mod:`omnispectral.mosaic.sources`), open or as a directory; everything the
        panorama's metadata needs (camera models, sensitivities, rig snapshot) is read from them, never
        from a rig file or a session.
    output
        The panorama store (``.zarr`` directory); an interrupted run with the same parameters resumes.
    options
        Every choice below as one :class:`~omnispectral.mosaic.options.MosaicOptions` (then leave the
        keywords at their defaults).
    width
        Panorama width (height = width / 2); default :func:`~omnispectral.imaging.geometry.native_width` of
        camera A.
    tile
        Tile (and chunk) side in pixels.
    interp, blend, multiband_levels, gain_compensation
        Interpolation (:data:`omnispectral.mosaic.interp.METHODS`), blending
        (:data:`omnispectral.mosaic.blending.BLENDS`: ``"linear"``, the paper's, or ``"multiband"``), and
        per-direction gain compensation (:mod:`omnispectral.mosaic.gain`).
    scheduler, workers
        ``None`` for Dask's local threaded scheduler with ``workers`` threads (default: all cores),
        or a Dask distributed scheduler address / ``Client``.
    overwrite, compression
        Replace an existing store instead of resuming it; the chunks' compression.
    region
        ``(row0, row1, col0, col1)``: compute only the tiles meeting this window of level 0 (the
        rest stays NaN; a later run can add more).
    b_predictor
        The spectral prior's predictor of camera B's bands from A's
        (:func:`omnispectral.spectral.conditional.b_from_a_predictor`), used where B saw nothing
        (:mod:`omnispectral.mosaic.predict`); ``None`` fits one per tile to the tile's measured pixels.
    edge_model
        Give output pixels at straight edges their footprint's share of each side (:mod:`omnispectral.mosaic.edges`);
        False: the interpolated value alone.
    progress
        ``progress(stage, done, total)`` (:data:`omnispectral.progress.ProgressCallback`) per finished chunk;
        ``stage`` is ``"tiles"`` or ``"pyramid"``.

    Returns
    -------
    dict
        The run's summary, with ``repaired_chunks``: the chunks of a resumed store that were marked done but
        missing or damaged (their checksums, :meth:`~omnispectral.mosaic.store.PanoramaStore.chunk_problems`)
        and were computed again.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.4, Eq. (4) (polar coordinates of each directional image), Sec. 4.5,
       Fig. 8 (the omnidirectional image from the directions, overlaps blended linearly), Fig. 14 (gigapixel).
    .. [2] R. G. Keys, "Cubic convolution interpolation for digital image processing", IEEE TASSP 29(6), 1981
       (``interp="cubic"`` and ``"cubic-clamped"``).
    .. [3] M. Unser, A. Aldroubi, M. Eden, "Fast B-spline transforms for continuous image representation and
       interpolation", IEEE TPAMI 13(3), 1991 (``interp="spline"``, the default).
    .. [4] P. J. Burt, E. H. Adelson, "A multiresolution spline with application to image mosaics", ACM TOG
       2(4), 1983 (``blend="multiband"``).
    .. [5] M. Brown, D. G. Lowe, "Automatic panoramic image stitching using invariant features", IJCV 74(1),
       2007, Sec. 6, Eq. (29) (``gain_compensation``).
    """
    options = MosaicOptions.from_keywords(
        options, width=width, tile=tile, interp=interp, blend=blend, multiband_levels=multiband_levels,
        gain_compensation=gain_compensation, scheduler=scheduler, workers=workers, overwrite=overwrite,
        compression=compression, region=region, b_predictor=b_predictor, edge_model=edge_model)
    progress = optional_progress(progress)
    t_start = time.perf_counter()
    output = Path(output).absolute()  # tasks may run in Dask worker processes started in other directories
    # the folder holding the store is locked (reentrant): a product's lock keeps a mosaic out while it is processed
    with directory_lock(output.parent, "mosaic"):
        return _mosaic_locked(source, output, options, progress, t_start)


def _mosaic_locked(source, output: Path, options: MosaicOptions, progress: ProgressCallback,
                   t_start: float) -> dict:
    """:func:`mosaic` while holding the lock of the store's folder."""
    merged = open_input(source)
    merged.check_files()
    gains = None
    if options.gain_compensation:
        gains = estimate_gains(merged)
    job = build_job(merged, Path(output), options, gains)
    width = job.canvas.width
    attrs = panorama_attributes(merged, job, options.gain_compensation)
    quality = job.has_quality and blend_method(options.blend).quality_layer
    store = PanoramaStore.create(output, width // 2, width, job.n_bands, options.tile, attrs, fingerprint(merged, job),
                                 overwrite=options.overwrite, compression=options.compression,
                                 quality_bands=N_QUALITY if quality else 0)
    damaged = store.unmark_damaged()  # a resumed store: chunks whose files are missing or damaged are redone
    t_tiles = time.perf_counter()
    tiles = tiles_in(store, options.region)
    computed = run_level0(job, store, tiles, options, progress)
    t_pyramid = time.perf_counter()
    run_pyramid(store, tiles, options, progress)
    store.set_display_windows()  # what OME-Zarr viewers open the panorama with
    t_end = time.perf_counter()
    summary = summarise(store, tiles, computed, {"prepare": t_tiles - t_start, "tiles": t_pyramid - t_tiles,
                                                 "pyramid": t_end - t_pyramid, "total": t_end - t_start}, job)
    summary["repaired_chunks"] = [{"file": str(p["path"].relative_to(store.path)), "problem": p["problem"]}
                                  for p in damaged]
    return summary
