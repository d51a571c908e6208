"""Names and defaults that the library defines and the command line offers, in a module that imports nothing heavy.

``omnispectral --help`` and ``omnispectral COMMAND --help`` build their parsers (:mod:`omnispectral.cli.parsers`)
from these values without importing NumPy, colour-science, OpenCV, SciPy or Zarr: the library modules that
need them import them from here.  Each value is written once, here; the module that owns it keeps offering it
under its name there (``omnispectral.rig.PRESETS``, ``omnispectral.product.process.DEFAULT_INTERP``,
``omnispectral.imaging.registration.WINDOWS``…), and the tables of methods by name are keyed by the names here, in
this order (``omnispectral.mosaic.interp.METHODS`` by :data:`INTERP_NAMES`, ``omnispectral.mosaic.blending.BLENDS``
by :data:`BLEND_NAMES`, ``omnispectral.product.sun_methods.SUN_METHODS`` by :data:`SUN_METHOD_NAMES`,
``omnispectral.imaging.lens.MODELS`` by :data:`LENS_MODEL_NAMES`).
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Mapping
from dataclasses import fields
from typing import Any

from omnispectral.errors import ConfigurationError

__all__ = [
    "BLEND_NAMES",
    "DEFAULT_BAND_LIMIT",
    "DEFAULT_BOARD",
    "DEFAULT_CAMERA",
    "DEFAULT_DATE",
    "DEFAULT_FILTERS",
    "DEFAULT_HDR_WEIGHT",
    "DEFAULT_ILLUMINANT",
    "DEFAULT_INTERP",
    "DEFAULT_MIN_CONFIDENCE",
    "DEFAULT_MULTIBAND_LEVELS",
    "DEFAULT_N_VIEWS",
    "DEFAULT_PREPROCESS",
    "DEFAULT_REGISTRATION",
    "DEFAULT_SQUARE_MM",
    "DEFAULT_SUBPIX_WINDOW",
    "DEFAULT_TARGET",
    "DEFAULT_TILE",
    "DETECTORS",
    "FORMATS",
    "HDR_WEIGHT_NAMES",
    "INTERP_NAMES",
    "LENS_MODEL_NAMES",
    "MIN_IMAGES",
    "PREPROCESS",
    "PRESETS",
    "REGISTRATION_NAMES",
    "RESPONSES",
    "SUN_METHOD_NAMES",
    "WINDOWS",
    "method_from",
    "options_or_keywords",
]

# ------------------------------------------------------------------ the rig (omnispectral.rig)
#: Built-in rigs (``omnispectral/data/rigs/NAME.toml``).
PRESETS = ("paper-timelapse", "paper-gigapixel", "small")

# ------------------------------------------------------------------ the spectral core (omnispectral.spectral.library)
DEFAULT_CAMERA = "Nikon 5100 (NPL)"
DEFAULT_FILTERS = ("wratten-34a", "sp18-standin")
DEFAULT_TARGET = "colorchecker"
DEFAULT_ILLUMINANT = "D65"

# ------------------------------------------------------------------ lens calibration (omnispectral.imaging.lens)
#: Distortion models offered, the keys of ``omnispectral.imaging.lens.MODELS``: standard k1 k2 p1 p2 k3, rational
#: (+ k4 k5 k6), thin-prism (+ s1..s4).
LENS_MODEL_NAMES = ("standard", "rational", "thin-prism")
DETECTORS = ("auto", "classic", "sb")
#: Fewest views with a detected board that calibration accepts (Zhang 2000 needs ≥ 3 for a general K).
MIN_IMAGES = 3
#: Default ``subpix_window_px``: "auto" (adapted to the corner spacing) or an int (11 = OpenCV's pipeline).
DEFAULT_SUBPIX_WINDOW: int | str = "auto"

# ------------------------------------------------------------------ HDR merge (omnispectral.imaging.hdr)
#: The merge's weights, the keys of ``omnispectral.imaging.hdr.WEIGHTS``: the paper's Eq. (2), inverse variance.
HDR_WEIGHT_NAMES = ("triangle", "noise")
#: ``process``'s weight: the triangle weight biases dark pixels upwards (docs/benchmarks.md, HDR merge).
DEFAULT_HDR_WEIGHT = "noise"

# ------------------------------------------------------------------ camera B (omnispectral.product.process)
#: The keys of ``omnispectral.product.process.REGISTRATIONS``: rig calibration + per-pixel parallax, the paper's
#: one offset per direction.
REGISTRATION_NAMES = ("parallax", "paper")
DEFAULT_REGISTRATION = "parallax"

# ------------------------------------------------------------------ registration (omnispectral.imaging.registration)
WINDOWS = ("hann", "tukey", "none")
PREPROCESS = ("sqrt", "none", "log", "gradient")
#: Fraction of Nyquist kept in each axis (Takita et al.'s ``K/M``), chosen by benchmark
#: (``benchmarks/bench_registration.py``; docs/benchmarks.md).
DEFAULT_BAND_LIMIT = 0.75
DEFAULT_PREPROCESS = "sqrt"
#: Peak height below which a whole-image registration is not trusted and the calibrated offset is
#: used instead.  Measured (docs/benchmarks.md, "Registration"): pure CMV2000 noise peaks at 0.03-0.04
#: (256 px) and 0.01 (1024 px); textured crops of real panoramas give 0.3-0.99.  Images smaller than
#: about 128 px have higher noise peaks: raise the threshold there (see
#: ``imaging.blockpoc.DEFAULT_BLOCK_MIN_CONFIDENCE``).
DEFAULT_MIN_CONFIDENCE = 0.15

# ------------------------------------------------------------------ the mosaic (omnispectral.mosaic)
#: Interpolation methods, the keys of ``omnispectral.mosaic.interp.METHODS`` in this order.
INTERP_NAMES = ("linear", "cubic", "spline", "lanczos", "cubic-clamped")
#: Blending methods, the keys of ``omnispectral.mosaic.blending.BLENDS``: ``linear`` (the paper's) and ``multiband``.
BLEND_NAMES = ("linear", "multiband")
DEFAULT_MULTIBAND_LEVELS = 4
#: Tile (and chunk) side of the panorama store, px (``omnispectral.mosaic.options``).
DEFAULT_TILE = 512

# ------------------------------------------------------------------ capture (omnispectral.capture)
#: Chessboard pairs recorded by default (``capture.calviews``): six put B at infinity within 0.03 px of the truth on
#: the small rig and within about 0.05 px at full scale (9 x 6 board; docs/benchmarks.md, "Calibration views").
DEFAULT_N_VIEWS = 6
#: How imported images' values relate to light (``capture.importer``).
RESPONSES = ("auto", "linear", "srgb")

# ------------------------------------------------------------------ the simulator (omnispectral.sim)
#: Inner corners and square side of the simulated board (``sim.boardviews``; an A2-size print: 0.72 × 0.54 m with
#: its margin).
DEFAULT_BOARD = (9, 6)
DEFAULT_SQUARE_MM = 60.0
#: Day of a simulated capture unless one is given (``sim.scenes``): the summer solstice (the paper's captures are
#: from 2016-2017 in Japan).
DEFAULT_DATE = _dt.date(2017, 6, 21)

# ------------------------------------------------------------------ the product (omnispectral.product)
#: Interpolation of ``process`` and of the ``mosaic`` command (``product.process``): Keys cubic clamped to the 2 × 2
#: neighbours' range (``mosaic.interp``): sharper than bilinear on texture and edges, and like it never overshoots.
DEFAULT_INTERP = "cubic-clamped"
#: The sun's recovery methods, the keys of ``omnispectral.product.sun_methods.SUN_METHODS``: ``auto`` and the
#: methods in order of preference, then ``none``.
SUN_METHOD_NAMES = ("auto", "nd-bracket", "diffuse-reference", "sky-model", "none")
#: Export formats (``product.exports``).
FORMATS = ("spectral-exr", "envi", "rgb-exr", "hdr", "png", "jpg", "uncertainty")


def method_from(table: Mapping[str, Any], name: str, what: str) -> Any:
    """The entry called ``name`` of a method table (a ``METHODS``-style dict: name → implementation).

    Parameters
    ----------
    table
        The table; its keys are the valid names, in the order messages list them.
    name
        The name asked for.
    what
        What the table chooses, for the message (``"interpolation"``, ``"blend"``…).

    Returns
    -------
    object
        ``table[name]``.

    Raises
    ------
    ConfigurationError
        ``unknown WHAT 'NAME'; expected one of A, B, …`` for a name the table does not hold.
    """
    try:
        return table[name]
    except (KeyError, TypeError):
        raise ConfigurationError(f"unknown {what} {name!r}; expected one of {', '.join(table)}") from None


def options_or_keywords(cls: type, options: Any, keywords: dict[str, Any]) -> Any:
    """An entry point's options dataclass: ``options`` as given, or ``cls(**keywords)`` when it is ``None``.

    Parameters
    ----------
    cls
        The options dataclass (its fields are the entry point's keywords).
    options
        Options built by the caller, or ``None``.
    keywords
        The entry point's keywords.  With ``options`` given, each must be left at its default: the two ways of
        choosing do not mix.

    Returns
    -------
    object
        The validated options (``cls`` validates itself when built).

    Raises
    ------
    ConfigurationError
        Naming the keywords given beside ``options``.
    """
    if options is None:
        return cls(**keywords)
    defaults = {f.name: f.default for f in fields(cls)}
    mixed = sorted(k for k, v in keywords.items() if v is not defaults[k] and v != defaults[k])
    if mixed:
        raise ConfigurationError(f"give either options= or keywords, not both (keywords: {', '.join(mixed)})")
    return options
