"""Block correspondences between camera A and camera B, per direction: the measurements of the session fit.

The paper registers B to A by one POC offset per direction (Hirai et al. 2018, Sec. 4.3, Eq. (3)); the
session fit of B's mounting (:mod:`omnispectral.product.rigfit`) instead pools many local POC
measurements of every direction.  Per direction, B's merged image is resampled onto A's grid for points at
infinity with the rig file's mounting (:func:`~omnispectral.product.pairgeometry.warp_b_onto_a`) and
registered block by block (POC, :func:`~omnispectral.imaging.blockpoc.measure_blocks`, whole-vector outlier
rule); a reliable block at A's pixel ``p`` whose content moved by ``d`` on A's grid gives the B pixel

.. math:: q = M(p + d),

``M`` the A → B map at infinity (:func:`~omnispectral.product.pairgeometry.cached_maps`, interpolated
linearly): where B saw the same content.  Large sensors are measured binned (to about
:data:`~omnispectral.imaging.binning.CALIBRATION_ANALYSIS_PX`) and positions brought back to full
pixels.  Each block keeps its normalised structure tensor ``J`` (how well each direction of its shift is
measured: an edge measures only the shift across it, the aperture problem) and its POC confidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from omnispectral.imaging.binning import CALIBRATION_ANALYSIS_PX, analysis_factor, bin_image, binned_to_full_px
from omnispectral.imaging.blockpoc import block_size_for, measure_blocks
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.parallax import PARALLAX_MIN_CONFIDENCE
from omnispectral.imaging.registration import as_gray
from omnispectral.product.pairgeometry import cached_maps, warp_b_onto_a

__all__ = ["RigMeasurements", "measure_direction"]


@dataclass
class RigMeasurements:
    """Block correspondences of all directions: A pixel, B pixel, confidence, direction index."""

    a_px: np.ndarray
    b_px: np.ndarray
    confidence: np.ndarray
    direction: np.ndarray
    #: the block's normalised structure tensor ``(jxx, jxy, jyy)``: how well each direction of the shift is
    #: measured (an edge measures only the shift across it: the aperture problem)
    tensor: np.ndarray

    @classmethod
    def empty(cls) -> RigMeasurements:
        """No correspondences (to :meth:`extend`).

        Returns
        -------
        RigMeasurements
            Zero blocks.
        """
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, int), np.zeros((0, 3)))

    def extend(self, other: RigMeasurements) -> None:
        """Append another set's blocks (in place).

        Parameters
        ----------
        other
            The blocks to append.
        """
        for name in ("a_px", "b_px", "confidence", "direction", "tensor"):
            setattr(self, name, np.concatenate([getattr(self, name), getattr(other, name)]))

    def subset(self, idx) -> RigMeasurements:
        """The blocks selected by ``idx``.

        Parameters
        ----------
        idx
            Index array or boolean mask over the blocks.

        Returns
        -------
        RigMeasurements
            The selected blocks.
        """
        return RigMeasurements(*(getattr(self, n)[idx] for n in ("a_px", "b_px", "confidence", "direction",
                                                                   "tensor")))


def measure_direction(direction: int, image_a: np.ndarray, image_b: np.ndarray, model_a: CameraModel,
                      model_b: CameraModel, min_confidence: float = PARALLAX_MIN_CONFIDENCE) -> RigMeasurements:
    """Reliable block correspondences (A pixel → B pixel) of one direction (module docstring).

    Parameters
    ----------
    direction
        The direction's index (kept with its blocks).
    image_a, image_b
        The direction's merged images of camera A and camera B ``(H, W, C)``.
    model_a, model_b
        Camera A's and camera B's models (B: the rig file's).
    min_confidence
        Smallest POC confidence of a block.

    Returns
    -------
    RigMeasurements
        The direction's reliable blocks (A and B pixel positions in full pixels).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.3, Eq. (3) (POC registration of camera B to camera A; here measured
       block by block to fit B's mounting).
    .. [2] C. D. Kuglin, D. C. Hines, "The phase correlation image alignment method", Proc. IEEE Int. Conf. on
       Cybernetics and Society, 163-165, 1975.
    .. [3] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration
       based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003.
    """

    maps = cached_maps(model_a, model_b)
    warped, seen = warp_b_onto_a(image_b, maps)
    # large sensors are measured binned (a 2048-px image in 2 x 2 bins): the blocks then see as much of the
    # scene as on a 1024-px sensor, at a quarter of the cost; positions are brought back to full pixels
    f = analysis_factor(model_a.width, model_a.height, CALIBRATION_ANALYSIS_PX)
    block = block_size_for(model_a.width // f, model_a.height // f)
    # whole-vector outliers: the fit's far anchor is tuned on the blocks this rule keeps (the edge-aware
    # rule of the per-pixel parallax adds edge blocks that moved the anchor by pixels on one session)
    bs = measure_blocks(as_gray(bin_image(image_a, f)), as_gray(bin_image(warped, f)), block, min_confidence,
                        edge_aware=False)
    conf = bs.confidence
    gy, gx = np.meshgrid(binned_to_full_px(bs.y_px, f), binned_to_full_px(bs.x_px, f), indexing="ij")
    tx, ty = gx + bs.dx * f, gy + bs.dy * f
    ok = bs.reliable & _inside(seen, gx, gy, block * f) & _inside(seen, tx, ty, block * f)
    if not ok.any():
        return RigMeasurements.empty()
    a_px = np.stack([gx[ok], gy[ok]], axis=-1)
    tx, ty = tx[ok].astype(np.float32)[:, None], ty[ok].astype(np.float32)[:, None]
    mx = cv2.remap(maps[0], tx, ty, cv2.INTER_LINEAR).reshape(-1)
    my = cv2.remap(maps[1], tx, ty, cv2.INTER_LINEAR).reshape(-1)
    b_px = np.stack([mx, my], axis=-1).astype(np.float64)
    good = np.isfinite(b_px).all(axis=1) & (b_px > -1e5).all(axis=1)
    return RigMeasurements(a_px[good], b_px[good], conf[ok][good].astype(np.float64),
                           np.full(int(good.sum()), int(direction)), bs.tensor[ok][good])


def _inside(seen: np.ndarray, x: np.ndarray, y: np.ndarray, block: int) -> np.ndarray:
    h, w = seen.shape
    half = block / 2
    ok = (x - half >= 0) & (x + half <= w - 1) & (y - half >= 0) & (y + half <= h - 1)
    xi = np.clip(np.rint(x).astype(int), 0, w - 1)
    yi = np.clip(np.rint(y).astype(int), 0, h - 1)
    return ok & seen[yi, xi]
