"""Spectral curves: loading, validation and resampling on a wavelength grid.

A :class:`SpectralSet` is a set of curves sampled on one wavelength axis: camera
sensitivities (paper Eq. (5), :math:`R_i(\\lambda)`), filter transmittances, illuminant spectral
power distributions (:math:`E(\\lambda)`) or surface reflectances.  The default grid is
400-700 nm every 5 nm (61 samples), the grid on which the paper's NRMSE is defined.

User curves come from CSV files with a header row ``wavelength_nm,<name>,<name>...`` and one
row per wavelength.  Lines starting with ``#`` are comments.  Malformed files raise
:class:`~omnispectral.errors.InputFileError` naming the file, the line and the problem.

Resampling over wavelength is linear interpolation between the two neighbouring samples, written once
(:func:`resample_spectra`, NumPy's ``np.interp`` arithmetic, which colour-science's ``LinearInterpolator``
also uses) and, for applying it to many spectra at once, as a matrix (:func:`resample_matrix`, one matrix
product; its weights ``1 - w, w`` round differently from ``np.interp``'s slope form by at most one unit in
the last place, so each caller keeps the form whose numbers it was built on).  Both check the grids the
same way.  Two other interpolations are used on purpose: ``SpectralSet.resample(method="sprague")`` (CIE
167:2005's interpolator for smooth uniformly sampled data) and :meth:`SpectralSet.from_colour`, which
aligns colour-science distributions on different grids with colour-science's own interpolation.
"""

from __future__ import annotations

import csv
import io
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import colour
import numpy as np

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.io import atomic_write_text, read_text_file

__all__ = ["DEFAULT_WAVELENGTH_NM", "INTERPOLATIONS", "KINDS", "SpectralSet", "concatenate", "read_spectral_csv",
           "resample_matrix", "resample_spectra", "write_spectral_csv"]

DEFAULT_WAVELENGTH_NM = np.arange(400.0, 700.0 + 1e-9, 5.0)
"""The default wavelength grid: 400-700 nm every 5 nm (61 samples)."""

KINDS = ("sensitivity", "transmittance", "illuminant", "reflectance", "signal")
"""What a curve measures.  Transmittances and reflectances are fractions in [0, 1]."""

#: The interpolations of :meth:`SpectralSet.resample`.
INTERPOLATIONS = ("linear", "sprague")

_FRACTION_KINDS = ("transmittance", "reflectance")
_WAVELENGTH_HEADERS = ("wavelength_nm", "wavelength", "nm", "lambda_nm", "wl_nm")
# Measured curves carry small negative values from noise; beyond this share of the column
# maximum a negative value is an error, below it the value is clipped to zero.
_NEGATIVE_TOLERANCE = 5e-3


@dataclass(frozen=True)
class SpectralSet:
    """Curves sampled on a common wavelength axis.

    Attributes
    ----------
    wavelength_nm
        Strictly increasing sample wavelengths, shape ``(n,)``.
    values
        One curve per row, shape ``(m, n)``.
    names
        One name per curve.
    kind
        One of :data:`KINDS`.
    source
        Where the curves came from (file path or data set name), used in messages.
    notes
        Anything done to the data on loading that a user should know (e.g. percent scaling).
    """

    wavelength_nm: np.ndarray
    values: np.ndarray
    names: tuple[str, ...]
    kind: str
    source: str
    notes: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        wl = np.asarray(self.wavelength_nm, dtype=np.float64)
        v = np.atleast_2d(np.asarray(self.values, dtype=np.float64))
        object.__setattr__(self, "wavelength_nm", wl)
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))
        if self.kind not in KINDS:
            raise ConfigurationError(f"{self.source}: unknown spectral kind {self.kind!r}; expected {KINDS}")
        if wl.ndim != 1 or v.shape[1] != wl.size:
            raise ConfigurationError(
                f"{self.source}: {v.shape[1]} samples per curve but {wl.size} wavelengths"
            )
        if len(self.names) != v.shape[0]:
            raise ConfigurationError(f"{self.source}: {v.shape[0]} curves but {len(self.names)} names")
        if wl.size > 1 and np.any(np.diff(wl) <= 0):
            raise ConfigurationError(f"{self.source}: wavelengths are not strictly increasing")

    def __len__(self) -> int:
        return self.values.shape[0]

    def covers(self, wavelength_nm: np.ndarray) -> bool:
        """Whether this set's wavelength range contains all of ``wavelength_nm``.

        Parameters
        ----------
        wavelength_nm
            Wavelengths (nm), any shape.

        Returns
        -------
        bool
            True when every wavelength lies within the set's first and last sample (± 1e-6 nm).
        """
        wl = np.asarray(wavelength_nm, dtype=np.float64)
        return bool(wl.min() >= self.wavelength_nm[0] - 1e-6 and wl.max() <= self.wavelength_nm[-1] + 1e-6)

    def resample(self, wavelength_nm: np.ndarray | None = None, method: str = "linear") -> SpectralSet:
        """Resample every curve onto ``wavelength_nm`` (default: 400-700 nm / 5 nm).

        ``"linear"`` (no overshoot on the sharp edges of filter curves, the default) is
        :func:`resample_spectra`; ``"sprague"`` is colour-science's ``SpragueInterpolator`` (CIE
        167:2005's recommended interpolator for uniformly sampled smooth data; linear for fewer than
        six or unevenly spaced samples).  Curves other than ``"signal"`` are clipped at 0.

        Parameters
        ----------
        wavelength_nm
            The target grid (nm); ``None`` for :data:`DEFAULT_WAVELENGTH_NM`.
        method
            ``"linear"`` or ``"sprague"``.

        Returns
        -------
        SpectralSet
            The same curves on the grid (``self`` when the grid is already this set's).

        Raises
        ------
        InputFileError
            When the set's range does not cover the grid (extrapolation is refused), naming the source.
        ConfigurationError
            On an unknown ``method``.
        """
        wl = DEFAULT_WAVELENGTH_NM if wavelength_nm is None else np.asarray(wavelength_nm, dtype=np.float64)
        if not self.covers(wl):
            raise InputFileError(
                self.source,
                f"wavelength range {self.wavelength_nm[0]:g}-{self.wavelength_nm[-1]:g} nm does not cover "
                f"the grid {wl.min():g}-{wl.max():g} nm",
            )
        if self.wavelength_nm.size == wl.size and np.allclose(self.wavelength_nm, wl):
            return self
        if method not in INTERPOLATIONS:
            raise ConfigurationError(f"unknown interpolation {method!r}; expected one of {list(INTERPOLATIONS)}")
        inside = np.clip(wl, self.wavelength_nm[0], self.wavelength_nm[-1])
        if method == "sprague" and self.wavelength_nm.size >= 6 and np.allclose(
                np.diff(self.wavelength_nm), np.diff(self.wavelength_nm)[0]):
            out = np.empty((len(self), wl.size))
            for i, row in enumerate(self.values):
                out[i] = colour.SpragueInterpolator(self.wavelength_nm, row)(inside)
        else:
            out = resample_spectra(self.values, self.wavelength_nm, inside)
        if self.kind != "signal":
            out = np.maximum(out, 0.0)
        return SpectralSet(wl, out, self.names, self.kind, self.source, self.notes)

    def select(self, names: list[str] | tuple[str, ...]) -> SpectralSet:
        """The curves called ``names`` (case-insensitive), in that order.

        Parameters
        ----------
        names
            Curve names.

        Returns
        -------
        SpectralSet

        Raises
        ------
        ConfigurationError
            For a name the set does not have.
        """
        lookup = {n.lower(): i for i, n in enumerate(self.names)}
        missing = [n for n in names if n.lower() not in lookup]
        if missing:
            raise ConfigurationError(f"{self.source}: no curve named {missing}; available: {list(self.names)}")
        idx = [lookup[n.lower()] for n in names]
        return SpectralSet(self.wavelength_nm, self.values[idx], [self.names[i] for i in idx], self.kind,
                           self.source, self.notes)

    def subset(self, mask: np.ndarray) -> SpectralSet:
        """The curves where ``mask`` is true.

        Parameters
        ----------
        mask
            Boolean ``(m,)``.

        Returns
        -------
        SpectralSet
        """
        mask = np.asarray(mask, dtype=bool)
        return SpectralSet(self.wavelength_nm, self.values[mask],
                           [n for n, keep in zip(self.names, mask, strict=True) if keep],
                           self.kind, self.source, self.notes)

    @classmethod
    def from_colour(cls, data, kind: str, source: str, names=None) -> SpectralSet:
        """Build from a colour-science spectral distribution, multi-distribution or mapping of them.

        Distributions of a mapping on different grids are aligned on the common range with colour-science's
        own interpolation (``SpectralDistribution.align``).

        Parameters
        ----------
        data
            ``SpectralDistribution``, ``MultiSpectralDistributions`` or a mapping name → distribution.
        kind
            One of :data:`KINDS`.
        source
            Where the data came from (for messages).
        names
            Curve names (default: the data's).

        Returns
        -------
        SpectralSet
        """
        if isinstance(data, colour.MultiSpectralDistributions):
            return cls(data.wavelengths, data.values.T, names or data.labels, kind, source)
        if isinstance(data, colour.SpectralDistribution):
            return cls(data.wavelengths, data.values[None, :], names or [data.name], kind, source)
        # a mapping name -> SpectralDistribution, possibly on different grids
        items = list(data.items())
        wl = items[0][1].wavelengths
        for _, sd in items:
            lo, hi = max(wl[0], sd.wavelengths[0]), min(wl[-1], sd.wavelengths[-1])
            wl = wl[(wl >= lo) & (wl <= hi)]
        values = np.array([sd.copy().align(colour.SpectralShape(wl[0], wl[-1], wl[1] - wl[0])).values
                           for _, sd in items])
        return cls(wl, values, names or [k for k, _ in items], kind, source)


def concatenate(sets: list[SpectralSet], wavelength_nm: np.ndarray | None = None, source: str | None = None,
                method: str = "linear") -> SpectralSet:
    """Resample several sets onto one grid and stack their curves (names prefixed by source).

    Parameters
    ----------
    sets
        Sets of one kind.
    wavelength_nm
        The grid (default :data:`DEFAULT_WAVELENGTH_NM`).
    source
        The result's source (default the sources joined by ``+``).
    method
        Interpolation (:meth:`SpectralSet.resample`).

    Returns
    -------
    SpectralSet

    Raises
    ------
    ConfigurationError
        Without sets, or for sets of different kinds.
    """
    if not sets:
        raise ConfigurationError("no spectral sets to concatenate")
    wl = DEFAULT_WAVELENGTH_NM if wavelength_nm is None else np.asarray(wavelength_nm, dtype=np.float64)
    parts = [s.resample(wl, method=method) for s in sets]
    kinds = {s.kind for s in parts}
    if len(kinds) != 1:
        raise ConfigurationError(f"cannot concatenate spectral sets of different kinds {sorted(kinds)}")
    names = [f"{s.source}:{n}" for s in parts for n in s.names]
    return SpectralSet(wl, np.vstack([s.values for s in parts]), names, parts[0].kind,
                       source or "+".join(s.source for s in parts))


def _parse_float(text: str, path: Path, line: int, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputFileError(path, f"column {column!r}: {text.strip()!r} is not a number", line) from None
    if math.isnan(value) or math.isinf(value):
        raise InputFileError(path, f"column {column!r}: value is {text.strip()} (NaN or infinite)", line)
    if value != 0.0 and abs(value) < sys.float_info.min:
        return 0.0  # subnormal (e.g. 1e-320): below double precision, and its reciprocal overflows
    return value


_UNIT_RE = re.compile(r"^\s*#\s*units?\s*[:=]\s*(percent|%|fraction)\b", re.IGNORECASE | re.MULTILINE)


def _stated_unit(text: str) -> bool | None:
    """``True`` (percent) / ``False`` (fraction) from a ``# units: percent|fraction`` comment, else ``None``."""
    m = _UNIT_RE.search(text)
    return None if m is None else m.group(1).lower() in ("percent", "%")


def read_spectral_csv(path: str | Path, kind: str, percent: bool | None = None) -> SpectralSet:
    """Read curves from a CSV file ``wavelength_nm,<name>,<name>...``.

    Parameters
    ----------
    path
        The CSV file. Lines beginning with ``#`` and blank lines are ignored.
    kind
        One of :data:`KINDS`; transmittances and reflectances may be given in percent.
    percent
        ``True``/``False`` to state the unit of a transmittance or reflectance table;
        ``None`` reads a ``# units: percent|fraction`` comment, else detects it (a maximum above 1.5
        means percent, at most 1 a fraction; in between is refused as ambiguous) and says so in ``notes``.

    Raises
    ------
    InputFileError
        On a missing or unreadable file, a wrong header, a short row, a value that is not a
        number, NaN, wavelengths that are not strictly increasing, or a negative value
        (beyond 0.5 % of the curve's maximum, which is clipped as measurement noise).

    Returns
    -------
    SpectralSet
        The curves (transmittances and reflectances as fractions), with what was done to them in ``notes``.
    """
    path = Path(path)
    if kind not in KINDS:
        raise ConfigurationError(f"unknown spectral kind {kind!r}; expected one of {KINDS}")
    text = read_text_file(path, encoding="utf-8-sig")

    rows: list[tuple[int, list[str]]] = []
    reader = csv.reader(text.splitlines())
    try:
        for line_no, row in enumerate(reader, start=1):
            if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
                continue
            rows.append((line_no, row))
    except csv.Error as exc:  # a field above the csv module's limit (128 KiB), a NUL byte, a bad quote
        raise InputFileError(path, f"not a readable CSV table ({exc})", reader.line_num) from None
    if not rows:
        raise InputFileError(path, "no header row and no data")
    header_line, header = rows[0]
    header = [h.strip() for h in header]
    if header[0].lower() not in _WAVELENGTH_HEADERS:
        raise InputFileError(path, f"first header column is {header[0]!r}; expected 'wavelength_nm'", header_line)
    if len(header) < 2:
        raise InputFileError(path, "header names no curve after 'wavelength_nm'", header_line)
    names = header[1:]
    if any(not n for n in names):
        raise InputFileError(path, "a curve column has an empty name", header_line)
    if len(set(names)) != len(names):
        raise InputFileError(path, "duplicate curve names in header", header_line)
    if len(rows) < 2:
        raise InputFileError(path, "header only, no data rows")

    wl = np.empty(len(rows) - 1)
    values = np.empty((len(names), len(rows) - 1))
    lines = np.empty(len(rows) - 1, dtype=int)
    for j, (line_no, row) in enumerate(rows[1:]):
        if len(row) != len(header):
            raise InputFileError(path, f"{len(row)} fields, expected {len(header)} as in the header", line_no)
        wl[j] = _parse_float(row[0], path, line_no, header[0])
        for i, name in enumerate(names):
            values[i, j] = _parse_float(row[i + 1], path, line_no, name)
        lines[j] = line_no
        if j > 0 and wl[j] <= wl[j - 1]:
            raise InputFileError(
                path, f"wavelengths not strictly increasing ({wl[j - 1]:g} nm then {wl[j]:g} nm)", line_no
            )
    if wl[0] <= 0:
        raise InputFileError(path, f"wavelength {wl[0]:g} nm is not positive", int(lines[0]))

    notes: list[str] = []
    for i, name in enumerate(names):
        peak = max(float(values[i].max()), 0.0)
        j = int(np.argmin(values[i]))
        if values[i, j] < -_NEGATIVE_TOLERANCE * max(peak, 1e-12):
            raise InputFileError(path, f"column {name!r}: negative {kind} {values[i, j]:g}", int(lines[j]))
    if np.any(values < 0):
        notes.append("small negative values (measurement noise) clipped to 0")
        values = np.maximum(values, 0.0)

    if kind in _FRACTION_KINDS:
        peak = float(values.max())
        if percent is None:
            percent = _stated_unit(text)
        if percent is None and 1.0 + 1e-6 < peak <= 1.5:
            i, j = np.unravel_index(int(np.argmax(values)), values.shape)
            raise InputFileError(path, f"column {names[i]!r}: maximum {kind} {peak:g} is neither a fraction (<= 1) "
                                       f"nor plausibly percent; state the unit with a '# units: percent' or "
                                       f"'# units: fraction' comment line", int(lines[j]))
        is_percent = peak > 1.5 if percent is None else percent
        if is_percent:
            if peak > 100.0 + 1e-6:
                i, j = np.unravel_index(int(np.argmax(values)), values.shape)
                raise InputFileError(path, f"column {names[i]!r}: {kind} {peak:g} % exceeds 100 %", int(lines[j]))
            values = values / 100.0
            notes.append(f"{kind} read as percent (maximum {peak:g}) and converted to fraction")
        else:
            if peak > 1.0 + 1e-6:
                i, j = np.unravel_index(int(np.argmax(values)), values.shape)
                raise InputFileError(path, f"column {names[i]!r}: {kind} {peak:g} exceeds 1 (fraction)", int(lines[j]))
            notes.append(f"{kind} read as fraction (maximum {peak:g})")
    return SpectralSet(wl, values, names, kind, str(path), tuple(notes))


def write_spectral_csv(spectral_set: SpectralSet, path: str | Path, comment: str | None = None) -> Path:
    """Write curves as ``wavelength_nm,<name>...`` CSV, atomically (temporary name, then rename).

    Parameters
    ----------
    spectral_set
        The curves.
    path
        The file.
    comment
        Written first as ``#`` lines.

    Returns
    -------
    pathlib.Path
        The written file.
    """

    buf = io.StringIO()
    for c in (comment or "").splitlines():
        buf.write(f"# {c}\n")
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["wavelength_nm", *spectral_set.names])
    for j, wl in enumerate(spectral_set.wavelength_nm):
        writer.writerow([f"{wl:g}", *(f"{v:.6g}" for v in spectral_set.values[:, j])])
    return atomic_write_text(path, buf.getvalue())


def _check_grids(src: np.ndarray, dst: np.ndarray, refuse_outside: bool) -> None:
    """The checks of both resampling forms: a strictly increasing source grid of at least 2 samples and, when
    ``refuse_outside``, a target grid within it (± 1e-9 nm)."""
    if src.ndim != 1 or src.size < 2 or np.any(np.diff(src) <= 0):
        raise ConfigurationError("source wavelengths must be a strictly increasing 1-D array of at least 2 values")
    if refuse_outside and dst.size and (dst.min() < src[0] - 1e-9 or dst.max() > src[-1] + 1e-9):
        raise ConfigurationError(f"wavelength range {src[0]:g}-{src[-1]:g} nm does not cover {dst.min():g}-"
                                 f"{dst.max():g} nm")


def resample_spectra(values, from_nm, to_nm, outside: str | float = "error") -> np.ndarray:
    """Linear interpolation of spectra over wavelength: the package's one spectral resampling.

    Each spectrum is interpolated by ``np.interp`` (so the values are bit for bit those of ``np.interp``
    and of colour-science's ``LinearInterpolator``).  For many spectra at once (images) the same
    interpolation as one matrix is :func:`resample_matrix`.

    Parameters
    ----------
    values
        Spectra ``(..., len(from_nm))``, any real dtype (computed in float64).
    from_nm
        Their wavelengths (nm): strictly increasing, at least 2.
    to_nm
        The wavelengths to interpolate at (nm), any shape.
    outside
        What a wavelength outside ``from_nm``'s range gets: ``"error"`` (refused, the default; up to 1e-9 nm
        outside counts as the end sample), ``"edge"`` (the nearest end sample's value) or a number.

    Returns
    -------
    numpy.ndarray
        float64 ``(..., *to_nm.shape)``.

    Raises
    ------
    ConfigurationError
        On a source grid that is not strictly increasing, spectra whose last axis does not match it, an unknown
        ``outside``, or (``outside="error"``) target wavelengths outside the source range.
    """
    src = np.asarray(from_nm, dtype=np.float64)
    dst = np.asarray(to_nm, dtype=np.float64)
    if isinstance(outside, str) and outside not in ("error", "edge"):
        raise ConfigurationError(f"unknown outside={outside!r}; expected 'error', 'edge' or a number")
    _check_grids(src, dst, refuse_outside=isinstance(outside, str) and outside == "error")
    fill = None if isinstance(outside, str) else float(outside)
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 0 or v.shape[-1] != src.size:
        raise ConfigurationError(f"spectra of shape {v.shape} do not match {src.size} wavelengths")
    flat = v.reshape(-1, src.size)
    out = np.empty((flat.shape[0], *dst.shape))
    for i, row in enumerate(flat):
        out[i] = np.interp(dst, src, row, left=fill, right=fill)
    return out.reshape(*v.shape[:-1], *dst.shape)


def resample_matrix(from_nm: np.ndarray, to_nm: np.ndarray) -> np.ndarray:
    """The linear interpolation of :func:`resample_spectra` as a matrix, for many spectra at once.

    Row ``i`` holds ``1 - w`` and ``w`` at the two samples around ``to_nm[i]``; ``M @ spectrum`` equals
    :func:`resample_spectra` to within one unit in the last place (the weights round differently from
    ``np.interp``'s slope form).

    Parameters
    ----------
    from_nm
        Source wavelengths (nm): strictly increasing, at least 2.
    to_nm
        Target wavelengths (nm) within ``[from_nm[0], from_nm[-1]]`` (± 1e-9 nm).

    Returns
    -------
    numpy.ndarray
        ``M`` float64 ``(len(to_nm), len(from_nm))`` with ``values_to = M @ values_from``.

    Raises
    ------
    ConfigurationError
        On a source grid that is not strictly increasing or a target outside it (no extrapolation).
    """
    src = np.asarray(from_nm, dtype=np.float64)
    dst = np.asarray(to_nm, dtype=np.float64)
    _check_grids(src, dst, refuse_outside=True)
    j = np.clip(np.searchsorted(src, dst, side="right") - 1, 0, src.size - 2)
    w = np.clip((dst - src[j]) / (src[j + 1] - src[j]), 0.0, 1.0)
    m = np.zeros((dst.size, src.size))
    rows = np.arange(dst.size)
    m[rows, j] += 1.0 - w
    m[rows, j + 1] += w
    return m
