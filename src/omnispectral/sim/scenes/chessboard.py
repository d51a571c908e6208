"""A chessboard held in front of the rig, for the stereo calibration of camera B (``calibrate rig --chessboard``).

One flat Lambertian board: ``(cols + 1) × (rows + 1)`` squares of side ``square_m`` around
``cols × rows`` inner corners (OpenCV's convention), a white margin of one square, lit by a light
source of illuminance ``illuminance_lx``; behind it a uniform grey background at infinity.  The
board's pose is given in the world frame of :mod:`omnispectral.imaging.geometry` (metres, origin at
the head's rotation centre): ``centre_m``, and the unit axes ``right`` (along a row of corners) and
``down`` (along a column); the normal is ``right × down``.  The inner corner ``(i, j)`` (row ``j``,
column ``i``) lies at ``centre + ((i − (cols−1)/2) right + (j − (rows−1)/2) down) · square_m``.
"""

from __future__ import annotations

import math

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.sim.scenes.base import BandProjectionCache, Scene, render_rows
from omnispectral.sim.scenes.indoor import light_spectrum
from omnispectral.spectral.curves import DEFAULT_WAVELENGTH_NM

__all__ = ["ChessboardScene"]

#: Reflectance of the black squares, the white squares and margin, and the background (spectrally flat).
BLACK_REFLECTANCE, WHITE_REFLECTANCE, BACKGROUND_REFLECTANCE = 0.04, 0.80, 0.30


class ChessboardScene(Scene):
    """One chessboard at a given pose (module docstring)."""

    kind = "chessboard"

    def __init__(self, board: tuple[int, int], square_m: float, centre_m, right, down, *,
                 light: str = "D65", illuminance_lx: float = 1000.0, wavelength_nm=None):
        super().__init__(DEFAULT_WAVELENGTH_NM if wavelength_nm is None else wavelength_nm)
        cols, rows = (int(x) for x in board)
        if cols < 2 or rows < 2 or not square_m > 0:
            raise ConfigurationError(f"a chessboard needs at least 2x2 inner corners and a positive square, got "
                                     f"{cols}x{rows}, {square_m} m")
        self.board, self.square_m = (cols, rows), float(square_m)
        self.centre_m = np.asarray(centre_m, np.float64)
        self.right = _unit(right)
        self.down = _unit(np.asarray(down, np.float64) - np.dot(down, self.right) * self.right)
        self.normal = np.cross(self.right, self.down)
        self.light = str(light)
        self.illuminance_lx = float(illuminance_lx)
        spectrum = light_spectrum(self.light, self.wavelength_nm)
        rho = np.array([BLACK_REFLECTANCE, WHITE_REFLECTANCE, BACKGROUND_REFLECTANCE])
        self._table64 = (rho[:, None] * spectrum[None, :]) * (self.illuminance_lx / math.pi)
        self._bands = BandProjectionCache()

    def white_radiance(self) -> np.ndarray:
        """Spectral radiance ``(n,)`` of the white squares."""
        return self._table64[1].copy()

    def corners_m(self) -> np.ndarray:
        """World positions ``(rows·cols, 3)`` of the inner corners, row by row (OpenCV's order)."""
        cols, rows = self.board
        j, i = np.mgrid[0:rows, 0:cols]
        a = (i.ravel() - (cols - 1) / 2) * self.square_m
        b = (j.ravel() - (rows - 1) / 2) * self.square_m
        return self.centre_m + a[:, None] * self.right + b[:, None] * self.down

    def material(self, d: np.ndarray, o: np.ndarray) -> np.ndarray:
        """Row of each ray ``d (N, 3)`` from ``o``: 0 black square, 1 white square or margin, 2 background."""
        denom = d @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.centre_m - o) @ self.normal) / denom
        hit = np.isfinite(t) & (t > 0)
        p = o + np.where(hit, t, 0.0)[:, None] * d - self.centre_m
        cols, rows = self.board
        a = p @ self.right / self.square_m + (cols + 1) / 2  # 0 at the left edge of the squares
        b = p @ self.down / self.square_m + (rows + 1) / 2
        inside = hit & (a >= -1) & (a < cols + 2) & (b >= -1) & (b < rows + 2)  # squares plus a one-square margin
        squares = (a >= 0) & (a < cols + 1) & (b >= 0) & (b < rows + 1)
        black = squares & ((np.floor(a) + np.floor(b)) % 2 == 0)
        return np.where(inside, np.where(black, 0, 1), 2)

    def _render(self, directions, origin_m, table: np.ndarray) -> np.ndarray:
        return render_rows(directions, origin_m, table, lambda d, o: (self.material(d, o), None))

    def spectral_radiance(self, directions, origin_m=(0.0, 0.0, 0.0)) -> np.ndarray:
        return self._render(directions, origin_m, self._table64.astype(np.float32))

    def band_radiance(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0)) -> np.ndarray:
        s = self.check_sensitivity(sensitivity)
        table = self._bands.get(s, lambda m: (self._table64 @ m.T).astype(np.float32))
        return self._render(directions, origin_m, table)

    def describe(self) -> dict:
        return {"kind": self.kind, "board": list(self.board), "square_m": self.square_m,
                "centre_m": self.centre_m.tolist(), "right": self.right.tolist(), "down": self.down.tolist(),
                "light": self.light, "illuminance_lx": self.illuminance_lx,
                "wavelength_nm": {"start": float(self.wavelength_nm[0]), "stop": float(self.wavelength_nm[-1]),
                                  "n": int(self.wavelength_nm.size)}}


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    n = np.linalg.norm(v)
    if not n > 0:
        raise ConfigurationError("a chessboard axis must not be zero")
    return v / n
