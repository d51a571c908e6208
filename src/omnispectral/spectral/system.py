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

__all__ = ["MultibandSystem", "build_system", "rgb_system", "six_band_system"]


@dataclass(frozen=True)
class MultibandSystem:
    """Spectral sensitivities of an m-band system sampled on ``wavelength_nm``.

    Attributes
    ----------
    wavelength_nm : numpy.ndarray
        Sample wavelengths ``(n,)`` in nm.
    sensitivity : numpy.ndarray
        Band sensitivities ``(m, n)``: camera channel times filter transmittance (without the sampling
        interval; :attr:`matrix` folds it in).
    band_names : tuple of str
        ``"A:R"``-style names: camera (filter slot) and channel.
    camera_of_band : numpy.ndarray
        Index of the physical camera behind each band ``(m,)``; bands of one camera share an
        exposure and a sensor.
    description : str
        Camera and filters, for reports.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Eqs. (5)-(6) (the spectral sensitivity functions ``R_i(λ)`` and the
       matrix ``R``), Sec. 3, Fig. 4 (six bands: two RGB cameras behind two colour filters).
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
        """R of Eq. (6) with the sampling interval folded in, so ``rho = R @ e``.

        Returns
        -------
        numpy.ndarray
            ``(m, n)`` float64: :attr:`sensitivity` times each sample's width in nm (the grid step on a
            uniform grid, the span between midpoints otherwise), so ``R @ e`` approximates
            ``∫ E(λ) R_i(λ) dλ`` by the rectangle rule.

        References
        ----------
        .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
           J. Imaging 4(4):53, 2018, Eq. (6) (``ρ = R e + σ``, ``R`` of size bands × n).
        """
        return self.sensitivity * _sample_widths_nm(self.wavelength_nm)[None, :]

    def response(self, spectra: np.ndarray) -> np.ndarray:
        """Noise-free band values ``s = R e`` (Eq. (6)) for spectra ``(..., n)`` -> ``(..., m)``.

        Parameters
        ----------
        spectra : array_like
            ``(..., n)`` spectra sampled on :attr:`wavelength_nm`, per nm (e.g. spectral radiance, or relative
            spectral power).

        Returns
        -------
        numpy.ndarray
            ``(..., m)`` band values ``Σ_λ E(λ) R_i(λ) Δλ``: the spectra's unit times nm, times the
            sensitivities' unit.

        References
        ----------
        .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
           J. Imaging 4(4):53, 2018, Eq. (5) (the signal ``s_i = ∫ E(λ) R_i(λ) dλ``), Eq. (6)
           (``s = R e``).
        """
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
    """The paper's six-band system: one camera model behind two filters (default 34A + SP-18 stand-in).

    Parameters
    ----------
    camera : str
        A camera sensitivity set of :func:`~omnispectral.spectral.library.load_camera` (name or CSV path).
    filters : tuple of str
        The filters in front of cameras A and B (:func:`~omnispectral.spectral.library.load_filter`).
    wavelength_nm : ndarray, optional
        The wavelength grid (default 400-700 nm every 5 nm).

    Returns
    -------
    MultibandSystem
        Six bands ``A:R A:G A:B B:R B:G B:B``; ``matrix (6, n)`` the system matrix R of Eq. (6).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System
       for Omnidirectional Scene Capture", J. Imaging 4(4):53, 2018, Sec. 2 and Eq. (6).
    """
    return build_system(load_camera(camera), [load_filter(f) for f in filters], wavelength_nm)


def rgb_system(camera: str = DEFAULT_CAMERA, wavelength_nm: np.ndarray | None = None) -> MultibandSystem:
    """The three-band comparison system: the same camera with no filter (paper Sec. 5.2)."""
    return build_system(load_camera(camera), [load_filter("none")], wavelength_nm)
