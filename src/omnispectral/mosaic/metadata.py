"""What a mosaic run records: the panorama store's metadata, the fingerprint that decides whether a run may resume
a store, and the summary the run returns.

:func:`panorama_attributes` is the store's ``omnispectral`` attribute group: bands and their units (DN per second
of exposure), the bands' spectral sensitivities and the estimator recorded by the merge, the rig and session,
the equirectangular geometry (row 0 at latitude +90°, column 0 at longitude −180°, pixel centres at +0.5) and
the method (interpolation, blending, gains, B's predictor).  :func:`fingerprint` hashes what determines the
pixels (inputs' names and checksums, or paths, sizes and mtimes for inputs written without checksums; poses,
offsets, scales, camera models, parallax maps; grid and method):
another fingerprint makes another panorama.  :func:`summarise` reports sizes, tiles computed and skipped,
holes, timings in seconds, throughput in megapixels per second and the peak resident memory in MiB.
"""

from __future__ import annotations

import hashlib
import json
import resource

import numpy as np

from omnispectral.mosaic.blending import blend_method
from omnispectral.mosaic.sources import BAND_NAMES, MergedDirections
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.mosaic.tile import MosaicJob

__all__ = ["fingerprint", "panorama_attributes", "peak_rss_mb", "summarise"]


def panorama_attributes(merged: MergedDirections, job: MosaicJob, gain_compensation: bool) -> dict:
    """The store's ``omnispectral`` attributes: bands, sensitivities, estimator, rig, session, geometry, method.

    Parameters
    ----------
    merged
        The merged directions (their ``merged.json`` holds what the metadata needs).
    job
        The run's job (canvas and method).
    gain_compensation
        Whether per-direction gains were estimated (``job.gains`` are then recorded).

    Returns
    -------
    dict
        JSON-serialisable attributes.
    """
    meta = merged.meta
    system = meta.get("system")  # recorded by the merge (product.merge); None for directions made without it
    return {
        "bands": list(meta.get("band_names", BAND_NAMES)),
        "units": meta.get("units", "DN per second of exposure"),
        "camera_bands": meta.get("camera_bands"),
        "wavelength_nm": system["wavelength_nm"] if system else None,
        "sensitivities": system["sensitivity"] if system else None,
        "sensitivity_description": system["description"] if system else None,
        "estimator": meta.get("estimator"),
        "rig": meta.get("rig"),
        "session": meta.get("session"),
        "merged_directions": str(merged.path.resolve()),
        "cameras": meta.get("cameras"),
        "n_directions": len(merged.directions),
        "geometry": "equirectangular: row 0 at latitude +90, column 0 at longitude -180, pixel centres at +0.5; "
                    "world +Y up, longitude 0 = +Z, longitude +90 = -X (omnispectral.imaging.geometry)",
        "mosaic": {"width": job.canvas.width, "height": job.canvas.height, "interp": job.interp, "blend": job.blend,
                   "multiband_levels": job.multiband_levels if blend_method(job.blend).uses_levels else None,
                   "edge_model": "partial areas at straight edges (omnispectral.mosaic.edges)" if job.edge_model
                   else None,
                   "gain_compensation": gain_compensation,
                   "gains": job.gains.tolist() if gain_compensation else None,
                   "weights": "linear blending: tent (1 - |2(u+1/2)/W - 1|)(1 - |2(v+1/2)/H - 1|) per sensor",
                   "fill": "NaN where camera A covers no direction; camera B's bands predicted from A's where B "
                           "saw nothing (omnispectral.mosaic.predict; quality layer b_predicted)",
                   "b_predictor": job.b_predictor.to_dict() if job.b_predictor is not None else "per tile"},
    }


def fingerprint(merged: MergedDirections, job: MosaicJob) -> dict:
    """What determines the output: inputs (names and checksums, or paths, sizes and mtimes; poses, offsets,
    scales), grid and method.

    Parameters
    ----------
    merged
        The merged directions.
    job
        The run's job (its sources, gains, canvas and method).

    Returns
    -------
    dict
        ``inputs_sha256`` (SHA-256 of the inputs' description) and the grid and method.
    """
    h = hashlib.sha256()
    for img, geo in zip(job.images, job.geometry, strict=True):
        par = None if img.parallax is None else _file_identity(img.parallax, img.parallax_checksum)
        h.update(json.dumps([*_file_identity(img.path, img.checksum), img.pan_deg, img.tilt_deg,
                             img.scale, list(img.offset_px), geo.model.to_dict(), par], sort_keys=True).encode())
    h.update(job.gains.tobytes())
    predictor = job.b_predictor.to_dict() if job.b_predictor is not None else None
    return {"inputs_sha256": h.hexdigest(), "width": job.canvas.width, "tile": job.tile, "interp": job.interp,
            "blend": job.blend, "multiband_levels": job.multiband_levels, "b_predictor": predictor,
            "edge_model": job.edge_model}


def _file_identity(path, checksum: dict | None) -> list:
    """What identifies an input file: its name and checksum when the merge recorded one (a product moved to
    another directory, or a direction merged again into the same bytes, still resumes), else its absolute path,
    size and modification time (merged directions written before checksums were recorded)."""
    if checksum:
        return [path.name, checksum.get("crc32"), checksum.get("bytes")]
    st = path.stat()
    return [str(path.resolve()), st.st_size, st.st_mtime_ns]


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MiB (Linux ``ru_maxrss`` is in KiB).

    Returns
    -------
    float
        MiB.
    """
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def summarise(store: PanoramaStore, tiles: list[tuple[int, int]], computed: int, seconds: dict,
              job: MosaicJob) -> dict:
    """Summary of a run: output, sizes, tiles computed/skipped, holes, timings, throughput, peak memory.

    Parameters
    ----------
    store
        The panorama store.
    tiles
        The level-0 chunks the run covered.
    computed
        How many of them the run computed.
    seconds
        Wall time per phase (``prepare``, ``tiles``, ``pyramid``, ``total``), s.
    job
        The run's job.

    Returns
    -------
    dict
        ``output``, ``width``, ``height``, ``bands``, ``levels``, ``tile``, ``interp``, ``blend``,
        ``n_sources``, ``tiles``, ``tiles_computed``, ``tiles_skipped``, ``holes_px``, ``predicted_px`` and
        ``unmixed_px`` (camera B's bands predicted from A's, mixed in A's share at edges), sources per tile,
        ``max_map_error_px``, ``seconds``, ``megapixels_per_s`` and ``peak_rss_mb``.
    """
    all_markers = store.done_markers(0)
    markers = {t: all_markers[t] for t in tiles if t in all_markers}
    n_tiles = len(tiles)
    h, w = store.shapes[0]
    holes = sum(int(m.get("holes", 0)) for m in markers.values())
    n_src = [int(m.get("n_sources", 0)) for m in markers.values()]
    computed_px = sum(int(m.get("pixels", 0)) for t, m in markers.items() if m.get("run") == job.run_id)
    return {"output": str(store.path), "width": w, "height": h, "bands": store.n_bands, "levels": [list(s) for s in
                                                                                             store.shapes],
            "tile": store.tile, "interp": job.interp, "blend": job.blend, "n_sources": len(job.images),
            "tiles": n_tiles, "tiles_computed": computed, "tiles_skipped": n_tiles - computed,
            "holes_px": holes, **{k: sum(int(m.get(k, 0)) for m in markers.values())
                                  for k in ("predicted_px", "unmixed_px")},
            "sources_per_tile_mean": float(np.mean(n_src)) if n_src else 0.0,
            "sources_per_tile_max": max(n_src, default=0),
            "max_map_error_px": max((float(m.get("map_error_px", 0.0)) for m in markers.values()), default=0.0),
            "seconds": {k: round(v, 3) for k, v in seconds.items()},
            "megapixels_per_s": round(computed_px / 1e6 / seconds["tiles"], 3) if seconds["tiles"] > 0 else None,
            "peak_rss_mb": round(peak_rss_mb(), 1)}
