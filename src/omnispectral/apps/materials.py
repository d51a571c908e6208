"""Spectral materials for rendering: diffuse reflectances and metals, sampled at any wavelengths.

- :class:`Diffuse`: a Lambertian reflectance ``ρ(λ)`` (a measured curve or a constant).
- :class:`Conductor`: a smooth metal with complex refractive index ``n + ik`` per wavelength.  The
  built-in metals are tabulated in ``data/metals/``: silver and aluminium from Palik, *Handbook of
  Optical Constants of Solids* (1985), as tabulated by the LuxPop database and shipped with Mitsuba 3.
- :func:`conductor_reflectance`: the exact unpolarised Fresnel reflectance of a conductor (Born & Wolf,
  *Principles of Optics*, Sec. 14.2; the form of Pharr, Jakob & Humphreys, PBRT 3rd ed., Sec. 8.2.1),
  used to check the renderer and to describe the metals.

A material is "flat" when its reflectance does not depend on wavelength: only then is the six-band
fast path of :mod:`omnispectral.apps.render` exact.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.spectral.curves import read_spectral_csv, resample_spectra

__all__ = ["METALS", "Conductor", "Diffuse", "conductor_reflectance", "load_metal", "material_at"]

METALS = ("silver", "aluminium")
_DATA = Path(__file__).resolve().parents[1] / "data" / "metals"


def _interp(wavelength_nm: np.ndarray, table_nm: np.ndarray, values: np.ndarray, what: str) -> np.ndarray:
    wl = np.asarray(wavelength_nm, float)
    if wl.min() < table_nm[0] - 1e-9 or wl.max() > table_nm[-1] + 1e-9:
        raise ConfigurationError(f"{what} is tabulated on {table_nm[0]:g}-{table_nm[-1]:g} nm, not "
                                 f"{wl.min():g}-{wl.max():g} nm")
    return resample_spectra(values, table_nm, wl)


@dataclass(frozen=True)
class Diffuse:
    """Lambertian reflectance tabulated on ``wavelength_nm`` (a 0-d ``values`` is a constant)."""

    name: str
    wavelength_nm: np.ndarray
    values: np.ndarray

    @classmethod
    def constant(cls, name: str, value: float) -> Diffuse:
        """A wavelength-flat reflectance ``value`` (tabulated on 300-900 nm)."""
        return cls(name, np.array([300.0, 900.0]), np.array([value, value], float))

    @classmethod
    def from_csv(cls, path: str | Path) -> Diffuse:
        """A reflectance CSV as a material.

        Parameters
        ----------
        path
            ``wavelength_nm,<name>``, one curve (percent detected, :func:`read_spectral_csv`).

        Returns
        -------
        Diffuse

        Raises
        ------
        InputFileError
            For a file that does not hold exactly one reflectance curve.
        """

        s = read_spectral_csv(path, "reflectance")
        if len(s) != 1:
            raise InputFileError(path, f"a material file needs exactly one reflectance curve; found {len(s)}")
        return cls(s.names[0], np.asarray(s.wavelength_nm, float), np.asarray(s.values[0], float))

    def reflectance(self, wavelength_nm: np.ndarray) -> np.ndarray:
        """The reflectance at some wavelengths (linear interpolation, no extrapolation).

        Parameters
        ----------
        wavelength_nm
            Wavelengths (nm) within the table.

        Returns
        -------
        numpy.ndarray

        Raises
        ------
        ConfigurationError
            For wavelengths outside the table.
        """
        return _interp(wavelength_nm, self.wavelength_nm, self.values, f"reflectance {self.name!r}")

    @property
    def flat(self) -> bool:
        """Whether the reflectance does not depend on wavelength."""
        return bool(np.ptp(self.values) < 1e-9)


@dataclass(frozen=True)
class Conductor:
    """A smooth conductor with complex refractive index ``n(λ) + i k(λ)`` (in air)."""

    name: str
    wavelength_nm: np.ndarray
    n: np.ndarray
    k: np.ndarray

    def eta_k(self, wavelength_nm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``n`` and ``k`` at some wavelengths (linear interpolation, no extrapolation).

        Parameters
        ----------
        wavelength_nm
            Wavelengths (nm) within the table.

        Returns
        -------
        tuple
            ``(n, k)``.

        Raises
        ------
        ConfigurationError
            For wavelengths outside the table.
        """
        return (_interp(wavelength_nm, self.wavelength_nm, self.n, f"metal {self.name!r}"),
                _interp(wavelength_nm, self.wavelength_nm, self.k, f"metal {self.name!r}"))

    def reflectance(self, wavelength_nm: np.ndarray, cos_theta: float | np.ndarray = 1.0) -> np.ndarray:
        """Fresnel reflectance at some wavelengths (:func:`conductor_reflectance`).

        Parameters
        ----------
        wavelength_nm
            Wavelengths (nm) within the table.
        cos_theta
            Cosine of the incidence angle.

        Returns
        -------
        numpy.ndarray
        """
        n, k = self.eta_k(wavelength_nm)
        return conductor_reflectance(cos_theta, n, k)

    @property
    def flat(self) -> bool:
        """Whether ``n`` and ``k`` do not depend on wavelength."""
        return bool(np.ptp(self.n) < 1e-9 and np.ptp(self.k) < 1e-9)


@functools.lru_cache(maxsize=8)
def load_metal(name: str) -> Conductor:
    """A metal by name or file.

    Parameters
    ----------
    name
        ``silver`` (``ag``), ``aluminium`` (``al``, ``aluminum``) or a CSV ``wavelength_nm,n,k`` file.

    Returns
    -------
    Conductor

    Raises
    ------
    ConfigurationError
        For an unknown name that is not a file.
    InputFileError
        For a file that is not three columns with increasing wavelengths.
    """
    key = {"ag": "silver", "al": "aluminium", "aluminum": "aluminium"}.get(name.lower(), name.lower())
    path = _DATA / f"{key}.csv" if key in METALS else Path(name)
    if key not in METALS and not path.is_file():
        raise ConfigurationError(f"unknown metal {name!r}; expected one of {', '.join(METALS)} or a CSV file "
                                 "wavelength_nm,n,k")
    try:
        rows = [ln.split(",") for ln in path.read_text(encoding="utf-8").splitlines()
                if ln.strip() and not ln.lstrip().startswith("#")]
        if rows and rows[0][0].strip().lower().startswith("wavelength"):
            rows = rows[1:]  # the header line
        table = np.array([[float(x) for x in r] for r in rows], float)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputFileError(path, f"cannot be read as wavelength_nm,n,k ({exc})") from None
    if (table.ndim != 2 or table.shape[1] != 3 or table.shape[0] < 2 or np.any(np.diff(table[:, 0]) <= 0)
            or not np.isfinite(table).all()):
        raise InputFileError(path, "needs three columns wavelength_nm,n,k with increasing wavelengths")
    return Conductor(key if key in METALS else path.stem, table[:, 0], table[:, 1], table[:, 2])


def conductor_reflectance(cos_theta, n, k) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a conductor ``n + ik`` from air at incidence ``cos θ`` (exact).

    ``a² + b² = √((n² − k² − sin²θ)² + 4n²k²)``, ``2a² = a²+b² + n² − k² − sin²θ``;
    ``R_s = (a²+b² − 2a cos θ + cos²θ)/(a²+b² + 2a cos θ + cos²θ)``,
    ``R_p = R_s (cos²θ (a²+b²) − 2a cos θ sin²θ + sin⁴θ)/(cos²θ (a²+b²) + 2a cos θ sin²θ + sin⁴θ)``,
    ``R = (R_s + R_p)/2``.

    Parameters
    ----------
    cos_theta
        Cosine of the incidence angle (clipped to [0, 1]).
    n, k
        Real and imaginary parts of the refractive index.

    Returns
    -------
    numpy.ndarray
        The reflectance, broadcast over the inputs.
    """
    c = np.clip(np.asarray(cos_theta, float), 0.0, 1.0)
    n = np.asarray(n, float)
    k = np.asarray(k, float)
    s2 = 1.0 - c * c
    t0 = n * n - k * k - s2
    a2b2 = np.sqrt(t0 * t0 + 4 * n * n * k * k)
    a = np.sqrt(np.maximum(0.5 * (a2b2 + t0), 0.0))
    t1 = a2b2 + c * c
    t2 = 2 * a * c
    rs = (t1 - t2) / (t1 + t2)
    t3 = c * c * a2b2 + s2 * s2
    t4 = t2 * s2
    rp = rs * (t3 - t4) / (t3 + t4)
    return 0.5 * (rs + rp)


def material_at(material, wavelength_nm: np.ndarray) -> dict[str, np.ndarray]:
    """The parameters a renderer needs at some wavelengths.

    Parameters
    ----------
    material
        :class:`Diffuse` or :class:`Conductor`.
    wavelength_nm
        Wavelengths (nm).

    Returns
    -------
    dict
        ``{"reflectance"}`` or ``{"eta", "k"}`` → values at the wavelengths.
    """
    if isinstance(material, Conductor):
        n, k = material.eta_k(wavelength_nm)
        return {"eta": n, "k": k}
    return {"reflectance": material.reflectance(wavelength_nm)}
