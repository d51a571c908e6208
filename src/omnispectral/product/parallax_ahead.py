"""Camera B's per-pixel parallax measured while the merge goes on (stage 2b overlapping stage 2).

The HDR merge (Eqs. (1)-(2)) spends much of its time reading and checking frames, which leaves a core
idle part of the time; the parallax of a direction (:func:`~omnispectral.product.direction_parallax.
parallax_direction`) needs only that direction's merged images and camera B's mounting.  When the
mounting is known before the merge (chessboard views or a calibration file,
:mod:`omnispectral.product.rigsource`), :class:`ParallaxAhead` measures each direction on a worker thread
as soon as the merge has written it, from the files just written (the same input as the stage after the
merge: the results are identical), and writes its parallax file.  The files are recorded in
``merged.json`` by the stage after the merge (:func:`omnispectral.product.process.register_parallax`),
which measures whatever is not done yet on all threads.

References
----------
.. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
   J. Imaging 4(4):53, 2018, Fig. 5 (the processing flow: HDR synthesis, then registration of camera B).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnispectral.imaging.geometry import CameraModel
from omnispectral.mosaic.sources import MergedDirectionsWriter, entry_sources
from omnispectral.product.direction_parallax import parallax_direction

__all__ = ["MeasuredParallax", "ParallaxAhead", "measure_parallax"]


@dataclass(frozen=True)
class MeasuredParallax:
    """One direction's parallax, its file written: what ``merged.json`` records for it.

    Parameters
    ----------
    index : int
        The direction.
    file : str
        The parallax file's name in the merged directory.
    checksum : str
        Its checksum.
    info : dict
        The direction's parallax statistics (:meth:`~omnispectral.product.direction_parallax.DirectionParallax.
        stats`).
    offset_px : tuple of float
        Camera B's offset at infinity (px).
    """

    index: int
    file: str
    checksum: str
    info: dict
    offset_px: tuple[float, float]

    def record(self, writer: MergedDirectionsWriter) -> None:
        """Record it in ``merged.json`` (:meth:`MergedDirectionsWriter.record_parallax`)."""
        writer.record_parallax(self.index, self.file, self.checksum, self.info, self.offset_px)


def measure_parallax(merged_path: Path, entry: dict, model_a: CameraModel, model_b: CameraModel,
                     apply_far_offset: bool) -> MeasuredParallax:
    """Measure one direction's parallax from its merged images and write its file.

    Parameters
    ----------
    merged_path : pathlib.Path
        The merged-directions directory.
    entry : dict
        The direction's ``merged.json`` entry (its images written).
    model_a, model_b : CameraModel
        Camera A's model and camera B's calibrated one.
    apply_far_offset : bool
        Apply the measured offset at infinity (:func:`~omnispectral.product.direction_parallax.parallax_direction`).

    Returns
    -------
    MeasuredParallax
        The file written and what to record.

    References
    ----------
    .. [1] Hirai et al., J. Imaging 4(4):53, 2018, Sec. 4.3 (camera B registered to camera A).
    """
    sources = {s.camera: s for s in entry_sources(Path(merged_path).absolute(), entry)}
    reg = parallax_direction(sources["A"].read(), sources["B"].read(), model_a, model_b,
                             float(entry["pan_deg"]), float(entry["tilt_deg"]), apply_far_offset=apply_far_offset)
    par = reg.parallax
    data = np.stack([par.inv_depth_per_m, par.confidence, par.occlusion_code()], axis=-1)
    name, checksum = MergedDirectionsWriter(merged_path, {}).write_parallax(int(entry["index"]), data)
    return MeasuredParallax(int(entry["index"]), name, checksum, reg.stats(), tuple(reg.offset_px))


class ParallaxAhead:
    """Measures each direction's parallax on one worker thread as the merge writes it (module docstring).

    Use as ``merge_session(..., written=ahead.submit)`` inside ``with ahead:``; then :meth:`finished` gives the
    directions measured, and those not started are left to the stage after the merge.

    Parameters
    ----------
    merged_path : pathlib.Path
        The merged-directions directory the merge writes.
    model_a, model_b : CameraModel
        Camera A's model and camera B's calibrated one.
    apply_far_offset : bool
        As :func:`measure_parallax`.
    """

    def __init__(self, merged_path: Path, model_a: CameraModel, model_b: CameraModel, apply_far_offset: bool):
        self.args = (Path(merged_path), model_a, model_b, apply_far_offset)
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="parallax-ahead")
        self.futures: list[Future] = []

    def __enter__(self) -> ParallaxAhead:
        return self

    def __exit__(self, *exc) -> None:
        for f in self.futures:
            f.cancel()
        self.pool.shutdown(wait=True)

    def submit(self, entry: dict) -> None:
        """Queue the direction the merge has just written (its ``merged.json`` entry)."""
        if "B" in entry.get("images", {}):
            path, model_a, model_b, far = self.args
            self.futures.append(self.pool.submit(measure_parallax, path, entry, model_a, model_b, far))

    def finished(self) -> dict[int, MeasuredParallax]:
        """The directions measured: the one running is waited for, those not started are cancelled (the stage
        after the merge measures them on all threads).  Errors are raised here."""
        for f in self.futures:
            f.cancel()
        done = [f.result() for f in self.futures if not f.cancelled()]
        return {m.index: m for m in done}
