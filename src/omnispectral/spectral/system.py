"""The multiband camera system matrix R of paper Eqs. (5)-(6).

Each band is one camera colour channel behind one filter:
:math:`R_{c,f}(\\lambda) = S_c(\\lambda)\\,T_f(\\lambda)`.  Two RGB cameras behind two filters give
six bands; one camera with no filter gives the three-band RGB system the paper compares against.
The matrix includes the sampling interval, so ``R @ e`` approximates :math:`\\int E(\\lambda)
R_i(\\lambda)\\,d\\lambda` for a spectrum ``e`` sampled on the same grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.spectral.curves import DEFAULT_WAVELENGTH_NM, SpectralSet
from omnispectral.spectral.library import DEFAULT_CAMERA, DEFAULT_FILTERS, load_camera, load_filter


@dataclass(frozen=True)
class MultibandSystem:
    """Spectral sensitivities of an m-band system sampled on ``wavelength_nm``.

    Attributes
    ----------
    wavelength_nm
        Sample wavelengths ``(n,)``.
    sensitivity
        Band sensitivities ``(m, n)``: camera channel times filter transmittance.
    band_names
        ``"A:R"``-style names: camera (filter slot) and channel.
    camera_of_band
        Index of the physical camera behind each band ``(m,)``; bands of one camera share an
        exposure and a sensor.
    description
        Camera and filters, for reports.
    """

    wavelength_nm: np.ndarray
    sensitivity: np.ndarray
    band_names: tuple[str, ...]
    camera_of_band: np.ndarray
    description: str

    @property
    def n_bands(self) -> int:
        return self.sensitivity.shape[0]

    @property
    def matrix(self) -> np.ndarray:
        """R of Eq. (6) with the sampling interval folded in, so ``rho = R @ e``."""
        return self.sensitivity * _sample_widths_nm(self.wavelength_nm)[None, :]

    def response(self, spectra: np.ndarray) -> np.ndarray:
        """Noise-free band values ``s = R e`` (Eq. (6)) for spectra ``(..., n)`` -> ``(..., m)``."""
        return np.asarray(spectra) @ self.matrix.T

    def to_dict(self) -> dict:
        return {
            "description": self.description,
            "band_names": list(self.band_names),
            "camera_of_band": self.camera_of_band.tolist(),
            "wavelength_nm": self.wavelength_nm.tolist(),
            "sensitivity": self.sensitivity.tolist(),
        }


def _sample_widths_nm(wavelength_nm: np.ndarray) -> np.ndarray:
    """Trapezoid-free rectangle widths: the grid step for uniform grids, midpoint spans otherwise."""
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    if wl.size == 1:
        return np.ones(1)
    edges = np.concatenate([[wl[0] - (wl[1] - wl[0]) / 2], (wl[1:] + wl[:-1]) / 2, [wl[-1] + (wl[-1] - wl[-2]) / 2]])
    return np.diff(edges)


def build_system(camera: SpectralSet, filters: list[SpectralSet] | tuple[SpectralSet, ...],
                 wavelength_nm: np.ndarray | None = None) -> MultibandSystem:
    """Combine one camera's RGB sensitivities with each filter into a ``3 * len(filters)``-band system.

    The paper's rig has two identical cameras (A behind Kodak 34A, B behind Fujifilm SP-18), so
    the six bands are ``[S_R T_A, S_G T_A, S_B T_A, S_R T_B, S_G T_B, S_B T_B]``.
    """
    if not filters:
        raise ConfigurationError("at least one filter is needed (use load_filter('none') for a bare camera)")
    wl = DEFAULT_WAVELENGTH_NM if wavelength_nm is None else np.asarray(wavelength_nm, dtype=np.float64)
    cam = camera.resample(wl)
    rows, names, cams = [], [], []
    for k, f in enumerate(filters):
        t = f.resample(wl).values[0]
        slot = chr(ord("A") + k)
        for ch, s in zip(cam.names, cam.values, strict=True):
            rows.append(s * t)
            names.append(f"{slot}:{ch}")
            cams.append(k)
    desc = f"{cam.source} x [" + ", ".join(f.names[0] for f in filters) + "]"
    return MultibandSystem(wl, np.array(rows), tuple(names), np.array(cams), desc)


def six_band_system(camera: str = DEFAULT_CAMERA, filters: tuple[str, str] = DEFAULT_FILTERS,
                    wavelength_nm: np.ndarray | None = None) -> MultibandSystem:
    """The paper's six-band system: one camera model behind two filters (default 34A + SP-18 stand-in)."""
    return build_system(load_camera(camera), [load_filter(f) for f in filters], wavelength_nm)


def rgb_system(camera: str = DEFAULT_CAMERA, wavelength_nm: np.ndarray | None = None) -> MultibandSystem:
    """The three-band comparison system: the same camera with no filter (paper Sec. 5.2)."""
    return build_system(load_camera(camera), [load_filter("none")], wavelength_nm)
