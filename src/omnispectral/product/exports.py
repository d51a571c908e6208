"""Standard files from spectral and six-band panoramas: spectral OpenEXR, ENVI, Radiance HDR, RGB EXR, previews.

Every writer takes NumPy arrays (a region or a pyramid level of a product), writes to a temporary name
and renames into place.

- :func:`write_spectral_exr`: the spectral OpenEXR layout of Fichet, Pacanowski & Wilkie, "An OpenEXR
  Layout for Spectral Images", JCGT 10(3), 2021: emissive channels ``S0.<λ>nm`` (decimal comma, e.g.
  ``S0.550,0nm``), ``spectralLayoutVersion = "1.0"``, ``emissiveUnits = "W.m^-2.sr^-1"`` (the layout's one
  defined unit; the values' real unit, e.g. DN/s per unit of the system matrix, in ``omnispectral_units``),
  no ``polarisationHandedness`` (unpolarised: S0 only), an sRGB preview in ``R,G,B``, tiled, one level (the
  OpenEXR Python package writes corrupt mip-maps), float32 or half.  Values are finite and ≥ 0 (NaN,
  ±inf and negative estimates → 0).  Readable by colour-science's ``read_spectral_image_Fichet2021``.
  Product exports add ``mask.valid`` (1 covered, 0 where the written 0 means nothing was seen) and
  ``quality.b_predicted`` and ``quality.b_unmixed`` (:func:`validity_layers`).
- :func:`write_envi`: ENVI via Spectral Python, band names and ``wavelength`` in nm, ``data ignore value``
  where nothing covers a pixel.
- :func:`write_rgb_exr` / :func:`write_radiance_hdr`: linear Rec.709/sRGB-primaries RGB for
  image-based lighting (Blender, Mitsuba), from the spectra through the CIE 1931 observer; finite and ≥ 0
  (out-of-gamut channels clipped); the EXR declares ``chromaticities`` (Rec.709 primaries, D65 white) and
  ``envmap = latlong``, the ``.hdr`` the same primaries and white in ``PRIMARIES=``.
- :func:`tone_map_srgb` / :func:`write_preview`: an 8-bit sRGB preview (exposure to put the 99th
  luminance percentile at 1, Reinhard 2002 global operator ``L/(1+L)`` rescaled, sRGB encoding).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import spectral.io.envi as envi

from omnispectral.choices import FORMATS
from omnispectral.errors import ConfigurationError
from omnispectral.imaging.bracket import FLOAT_IMAGE_SUFFIXES, write_float_image
from omnispectral.io import atomic_path
from omnispectral.ownership import check_output_outside_inputs
from omnispectral.product.layout import open_product
from omnispectral.product.saturation import recovered_sun_mask, saturated_mask, saturation_level_dn_s
from omnispectral.product.spectra import SunOverlay, bands_to_linear_srgb, derived_b_layers, estimate_image
from omnispectral.spectral.colour import spectra_to_linear_srgb, srgb_encode

__all__ = ["CLIPPED_ESTIMATE_FRACTION", "ENVI_IGNORE_VALUE", "EXPORT_SUFFIXES", "FICHET_EMISSIVE_UNITS", "FORMATS",
           "HALF_MAX", "RADIANCE_PRIMARIES", "REC709_CHROMATICITIES", "SPECTRAL_LAYOUT_VERSION",
           "check_export_output", "export_product", "light_values", "reinhard_srgb8", "spectral_channel_name",
           "tone_map_srgb", "validity_layers", "with_radiance_primaries", "write_envi", "write_preview",
           "write_radiance_hdr", "write_rgb_exr", "write_spectral_exr"]

SPECTRAL_LAYOUT_VERSION = "1.0"
#: The one ``emissiveUnits`` value the Fichet 2021 layout defines (spectral radiance per nm, written per channel).
FICHET_EMISSIVE_UNITS = "W.m^-2.sr^-1"
#: Rec.709 / sRGB primaries and D65 white as OpenEXR's ``chromaticities`` (red, green, blue, white xy).
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)
#: Largest finite half-float.
HALF_MAX = 65504.0


def light_values(values: np.ndarray) -> np.ndarray:
    """``values`` as light: float32, NaN/±inf → 0, negative → 0 (a radiance is never negative; an estimate
    undershoots on noisy or saturated pixels, a colour outside the sRGB gamut has a negative channel)."""
    return np.maximum(np.nan_to_num(np.asarray(values, np.float32), nan=0.0, posinf=0.0, neginf=0.0), 0.0)


def _write_exr_channels(path: Path, header: dict, channels: dict[str, np.ndarray]) -> Path:
    """One-part OpenEXR written atomically (``header`` holds typed OpenEXR attributes)."""
    with atomic_path(path) as tmp, OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, **header}, channels) as f:
        f.write(str(tmp))
    return path


def spectral_channel_name(wavelength_nm: float, stokes: int = 0) -> str:
    """Fichet 2021 emissive channel name: ``S0.550,0nm`` (decimal comma, unit suffix)."""
    text = repr(float(wavelength_nm)).replace(".", ",")
    return f"S{stokes}.{text}nm"


def tone_map_srgb(rgb_linear: np.ndarray, percentile: float = 99.0) -> np.ndarray:
    """8-bit sRGB preview of linear RGB: scale so the ``percentile`` luminance is 1, Reinhard ``L/(1+L)``
    (rescaled so that 1 maps to 0.9), sRGB transfer function; NaN → 0."""
    rgb = np.nan_to_num(np.asarray(rgb_linear, np.float32), nan=0.0, posinf=0.0).clip(0)
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    ref = float(np.percentile(lum[lum > 0], percentile)) if np.any(lum > 0) else 1.0
    return reinhard_srgb8(rgb / np.float32(ref))


def reinhard_srgb8(rgb_exposed: np.ndarray) -> np.ndarray:
    """8-bit sRGB of exposure-scaled linear RGB (or one channel as grey): Reinhard 2002 global operator on
    luminance, ``L → 1.8 L/(1+L)`` (1 maps to 0.9), clipped, sRGB transfer function (IEC 61966-2-1); NaN → 0."""
    x = np.nan_to_num(np.asarray(rgb_exposed, np.float32), nan=0.0, posinf=0.0).clip(0)
    lx = x @ np.array([0.2126, 0.7152, 0.0722], np.float32) if x.shape[-1] == 3 else x[..., 0]
    scale = np.where(lx > 0, (1.8 * lx / (1.0 + lx)) / np.maximum(lx, 1e-12), 0.0)[..., None]
    y = np.clip(x * scale, 0, 1)
    return np.round(srgb_encode(y) * 255).astype(np.uint8)


def write_preview(path: str | Path, rgb_linear: np.ndarray) -> Path:
    """sRGB PNG/JPEG preview of a linear RGB image (:func:`tone_map_srgb`)."""

    path = Path(path)
    img = tone_map_srgb(rgb_linear)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img[..., ::-1])):
            raise ConfigurationError(f"{path}: OpenCV cannot write this format (use .png or .jpg)")
    return path


def validity_layers(bands: np.ndarray, b_rel_std: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The spectral EXR's extra channels: ``mask.valid`` (1 where a direction covers the pixel, 0 where the
    written 0 means nothing was seen) and, for six-band products, ``quality.NAME`` for each derived-B layer
    ``b_rel_std`` holds (:func:`~omnispectral.product.spectra.derived_b_layers`; ``b_predicted``: relative
    error of camera B's bands predicted from A's where B saw nothing, :mod:`omnispectral.mosaic.predict`;
    ``b_unmixed``: where an edge mixes B's two surfaces in A's share, :mod:`omnispectral.mosaic.unmix`; 0
    where B's own value stands)."""
    layers = {"mask.valid": np.isfinite(bands).all(axis=2).astype(np.float32)}
    for name, rel in b_rel_std.items():
        layers[f"quality.{name}"] = np.asarray(rel, np.float32)
    return layers


def write_spectral_exr(path: str | Path, spectra: np.ndarray, wavelength_nm: np.ndarray, *, units: str,
                       attributes: Mapping[str, str] | None = None, tile: int = 64, half: bool = False,
                       layers: Mapping[str, np.ndarray] | None = None) -> Path:
    """Spectral OpenEXR (Fichet et al. 2021 layout, emissive), tiled, with an sRGB preview in R, G, B.

    ``emissiveUnits`` is the layout's ``W.m^-2.sr^-1``; when ``units`` (the values' real unit) is another,
    it is recorded in ``omnispectral_units``.  Values are written finite and ≥ 0 (:func:`light_values`).
    ``half``: 16-bit floats; values above the half range (65504) are scaled by a power of two recorded in
    ``omnispectral_scale`` (stored value × scale = value in ``units``).  Extra ``attributes`` as strings;
    extra ``layers`` (channel name → ``(H, W)``, e.g. :func:`validity_layers`) are written as they are.
    """

    spectra = light_values(spectra)
    wl = np.asarray(wavelength_nm, float)
    if spectra.ndim != 3 or spectra.shape[2] != wl.size:
        raise ConfigurationError(f"spectra of shape {spectra.shape} do not match {wl.size} wavelengths")
    rgb = light_values(spectra_to_linear_srgb(spectra, wl))
    extra = {str(k): str(v) for k, v in (attributes or {}).items()}
    if units != FICHET_EMISSIVE_UNITS:
        extra["omnispectral_units"] = units
    dtype = np.float16 if half else np.float32
    if half:
        peak = float(max(spectra.max(initial=0.0), rgb.max(initial=0.0)))
        scale = 2.0 ** max(0, math.ceil(math.log2(peak / HALF_MAX))) if peak > HALF_MAX else 1.0
        spectra, rgb = spectra / np.float32(scale), rgb / np.float32(scale)
        extra["omnispectral_scale"] = repr(scale)
    channels = {spectral_channel_name(w): np.ascontiguousarray(spectra[..., i].astype(dtype)) for i, w in
                enumerate(wl)}
    for i, c in enumerate("RGB"):
        channels[c] = np.ascontiguousarray(rgb[..., i].astype(dtype))
    for name, layer in (layers or {}).items():
        channels[name] = np.ascontiguousarray(np.asarray(layer).astype(dtype))
    tiles = OpenEXR.TileDescription()
    tiles.xSize, tiles.ySize, tiles.mode = tile, tile, OpenEXR.ONE_LEVEL  # no mip-maps (see module docstring)
    header = {"type": OpenEXR.tiledimage, "tiles": tiles, "spectralLayoutVersion": SPECTRAL_LAYOUT_VERSION,
              "emissiveUnits": FICHET_EMISSIVE_UNITS, "chromaticities": REC709_CHROMATICITIES, **extra}
    return _write_exr_channels(Path(path), header, channels)


#: ENVI ``data ignore value`` of the pixels no direction covers (an export's values are light: never negative).
ENVI_IGNORE_VALUE = -1.0


def write_envi(path: str | Path, cube: np.ndarray, wavelength_nm: np.ndarray | None = None,
               band_names: list[str] | None = None, description: str = "",
               ignore: np.ndarray | None = None) -> Path:
    """ENVI image (``.hdr`` header + ``.img`` data, float32, band-sequential (BSQ) by Spectral Python) with
    wavelengths in nm and band names (``λ nm`` unless ``band_names`` are given); pixels where ``ignore``
    ``(H, W)`` is True hold :data:`ENVI_IGNORE_VALUE`, declared as the header's ``data ignore value``."""

    path = Path(path)
    if path.suffix.lower() != ".hdr":
        raise ConfigurationError(f"{path}: an ENVI export is named by its header, e.g. pano.hdr")
    cube = np.asarray(cube, np.float32)
    meta = {"description": description or "omnispectral export"}
    if wavelength_nm is not None:
        meta["wavelength"] = [f"{w:g}" for w in np.asarray(wavelength_nm, float)]
        meta["wavelength units"] = "nm"
        if band_names is None:
            band_names = [f"{w:g} nm" for w in np.asarray(wavelength_nm, float)]
    if band_names is not None:
        meta["band names"] = list(band_names)
    if ignore is not None and np.any(ignore):
        cube = cube.copy()
        cube[np.asarray(ignore, bool)] = ENVI_IGNORE_VALUE
        meta["data ignore value"] = f"{ENVI_IGNORE_VALUE:g}"
    data = path.with_suffix(".img")
    with atomic_path(path) as tmp_hdr, atomic_path(data) as tmp_img:
        envi.save_image(str(tmp_hdr), cube, metadata=meta, force=True, ext=tmp_img.suffix, interleave="bsq")
        # Spectral Python names the data file after the header; move it onto the reserved temporary name
        written = tmp_hdr.with_suffix(tmp_img.suffix)
        written.replace(tmp_img)
    return path


def write_rgb_exr(path: str | Path, rgb_linear: np.ndarray, attributes: Mapping[str, str] | None = None) -> Path:
    """Linear RGB OpenEXR (float32) for image-based lighting: Rec.709 primaries and D65 white declared in
    ``chromaticities``, ``envmap = latlong`` (equirectangular), values finite and ≥ 0."""

    rgb = light_values(rgb_linear)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ConfigurationError(f"an RGB image has shape (H, W, 3), not {rgb.shape}")
    header = {"type": OpenEXR.scanlineimage, "chromaticities": REC709_CHROMATICITIES,
              "envmap": OpenEXR.ENVMAP_LATLONG, **{str(k): str(v) for k, v in (attributes or {}).items()}}
    return _write_exr_channels(Path(path), header, {c: np.ascontiguousarray(rgb[..., i]) for i, c in enumerate("RGB")})


#: The Radiance header line declaring Rec.709/sRGB primaries and D65 white (red, green, blue, white xy).
RADIANCE_PRIMARIES = b"PRIMARIES= 0.640 0.330 0.300 0.600 0.150 0.060 0.3127 0.3290\n"


def with_radiance_primaries(encoded: memoryview) -> tuple[memoryview, bytes, memoryview]:
    """A Radiance file (OpenCV's encoding) in three pieces to write one after the other: its ``#?RADIANCE``
    signature line, :data:`RADIANCE_PRIMARIES`, and the rest (no copy of the pixels).

    The line goes right after the signature, before ``FORMAT=``: readers derived from Bruce Walter's ``rgbe.c``
    (older OpenCV among them) expect the blank line that ends the header right after ``FORMAT=``.
    """
    first = bytes(encoded[:64]).find(b"\n") + 1
    if bytes(encoded[:2]) != b"#?" or first == 0:
        raise ValueError("not a Radiance file: no #? signature line")
    return encoded[:first], RADIANCE_PRIMARIES, encoded[first:]


def write_radiance_hdr(path: str | Path, rgb_linear: np.ndarray) -> Path:
    """Radiance RGBE ``.hdr`` (values finite and ≥ 0: RGBE has no sign) declaring Rec.709/sRGB primaries and
    D65 white in its header (:data:`RADIANCE_PRIMARIES`)."""

    path = Path(path)
    rgb = light_values(rgb_linear)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ConfigurationError(f"{path}: Radiance .hdr holds an RGB image (H, W, 3), not {rgb.shape}")
    ok, encoded = cv2.imencode(".hdr", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise ConfigurationError(f"{path}: OpenCV could not encode the Radiance file")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        for piece in with_radiance_primaries(memoryview(encoded).cast("B")):
            fh.write(piece)
    return path


def check_export_output(fmt: str, output: str | Path, product: str | Path) -> None:
    """Refuse, before any work, an output that is a directory, has the wrong extension for ``fmt``, or
    lies inside the product (an export never overwrites a product's own files)."""

    out = Path(output)
    if out.is_dir():
        raise ConfigurationError(f"{out}: is a directory; give the export's file name (e.g. {out / 'pano'}"
                                 f"{EXPORT_SUFFIXES.get(fmt, ('.exr',))[0]})")
    allowed = EXPORT_SUFFIXES.get(fmt, tuple(FLOAT_IMAGE_SUFFIXES))
    if out.suffix.lower() not in allowed:
        raise ConfigurationError(f"{out}: a {fmt} export is written as {' or '.join(allowed)}, not "
                                 f"{out.suffix or 'a file without extension'}")
    check_output_outside_inputs([out], [product])  # exports never overwrite the product's own files


#: File extensions of each export format (``uncertainty``: any float image format).
EXPORT_SUFFIXES = {"png": (".png",), "jpg": (".jpg", ".jpeg"), "rgb-exr": (".exr",), "spectral-exr": (".exr",),
                   "hdr": (".hdr",), "envi": (".hdr",)}


def export_product(product: str | Path, fmt: str, output: str | Path, region: tuple[int, int, int, int] | None = None,
                   level: int = 0, max_bytes: int | None = None, half: bool = False) -> dict:
    """Write one standard file from a processed product (a region and/or a pyramid level of it).

    ``region`` is ``(row0, row1, col0, col1)`` in pixels of ``level``.  Spectral formats hold ``n``
    float32 values per pixel; an export whose array would exceed ``max_bytes`` (default: half the
    machine's memory) is refused before anything is computed, naming the size and the way out.
    ``half``: 16-bit floats in a spectral EXR.  Light formats (spectral EXR, ENVI, RGB EXR, HDR) hold finite
    values ≥ 0; beside a spectral EXR or ENVI file, ``NAME_saturated.png`` marks (255) the pixels saturated
    in every exposure (:mod:`omnispectral.product.saturation`: their values are lower bounds), when the
    product's rig snapshot says where clipping starts.  No path of this machine goes into the files.
    """

    if fmt not in FORMATS:
        raise ConfigurationError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    check_export_output(fmt, output, product)
    index, store, estimator = open_product(product)
    if not 0 <= level < len(store.shapes):
        raise ConfigurationError(f"level {level} does not exist; the product has levels 0-{len(store.shapes) - 1} "
                                 f"({', '.join(f'{w}x{h}' for h, w in store.shapes)})")
    h, w = store.shapes[level]
    r0, r1, c0, c1 = region if region is not None else (0, h, 0, w)
    if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w):
        raise ConfigurationError(f"region rows {r0}-{r1}, columns {c0}-{c1} is outside level {level} ({w}x{h})")
    n = len(estimator.wavelength_nm)
    per_px = {"spectral-exr": n + 3, "envi": n, "uncertainty": 2 * n}.get(fmt, store.n_bands)
    need = (r1 - r0) * (c1 - c0) * per_px * 4 * 2
    limit = max_bytes if max_bytes is not None else os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    if need > limit:
        raise ConfigurationError(f"a {fmt} export of {c1 - c0}x{r1 - r0} px needs about {need / 2**30:.1f} GiB of "
                                 f"memory (limit {limit / 2**30:.1f} GiB): use --level (e.g. {level + 1}) or --region")
    bands = store.read(level, slice(r0, r1), slice(c0, c1))
    extra: dict = {}
    wl = np.asarray(estimator.wavelength_nm)
    units = f"{index['units']} per unit of the system matrix"
    attrs = {"omnispectral_product": Path(product).resolve().name, "omnispectral_units": units,
             "omnispectral_region": f"level {level} rows {r0}-{r1} cols {c0}-{c1}",
             "omnispectral_geometry": "equirectangular; row 0 at latitude +90 of the full panorama, column 0 at -180"}
    sun = SunOverlay.of(store, level, bands.shape[:2], (r0, c0))
    derived_b = derived_b_layers(store, level, bands.shape[:2], (r0, c0))
    b_rel = np.maximum.reduce(list(derived_b.values())) if derived_b else None
    if fmt in ("png", "jpg"):
        path = write_preview(output, bands_to_linear_srgb(bands, estimator, sun))
    elif fmt in ("rgb-exr", "hdr"):
        rgb = bands_to_linear_srgb(bands, estimator, sun)
        path = write_rgb_exr(output, rgb, attrs) if fmt == "rgb-exr" else write_radiance_hdr(output, rgb)
    elif fmt == "uncertainty":
        spectra, std = estimate_image(bands, estimator, with_std=True, sun=sun, b_rel_std=b_rel)
        rms = np.sqrt(np.mean(std**2, axis=2))
        rel = rms / np.maximum(np.sqrt(np.mean(spectra**2, axis=2)), 1e-30)

        path = write_float_image(output, np.stack([rel, rms], axis=2), ["relative_std", "std_rms"], attrs)
    else:
        spectra = estimate_image(bands, estimator, sun=sun, b_rel_std=b_rel)
        if fmt == "spectral-exr":
            path = write_spectral_exr(output, spectra, wl, units=units, attributes=attrs, half=half,
                                      layers=validity_layers(bands, derived_b))
        else:
            path = write_envi(output, light_values(spectra), wl,
                              description=f"omnispectral {attrs['omnispectral_region']}",
                              ignore=~np.isfinite(bands).any(axis=2))
        extra["saturation"] = _write_saturation_mask(Path(output), store, level, bands, (r0, c0), spectra)
    return {"output": str(path), "format": fmt, "level": level, "region": [r0, r1, c0, c1],
            "width": c1 - c0, "height": r1 - r0, **extra}


#: An estimate counts as clipped (unreliable) when its most negative value exceeds this share of its peak.
CLIPPED_ESTIMATE_FRACTION = 0.1


def _write_saturation_mask(output: Path, store, level: int, bands: np.ndarray, origin: tuple[int, int],
                           spectra: np.ndarray) -> dict:
    """``OUTPUT_saturated.png`` beside an export: 255 where saturated in every exposure (a lower bound), 64
    where the pixel holds the recovered sun (:mod:`omnispectral.product.sun`: measured or, with the sky
    model, estimated), 128 where not saturated but the estimate went negative by more than
    ``CLIPPED_ESTIMATE_FRACTION`` of its peak before it was clipped to 0 (bands no spectrum explains: around
    the sun, where one camera clipped or the views disagree); what was found."""
    finite = np.isfinite(spectra).all(axis=2)
    values = np.where(finite[..., None], spectra, 0.0)  # uncovered pixels (NaN) are not clipped estimates
    clipped = finite & (-values.min(axis=2) > CLIPPED_ESTIMATE_FRACTION * np.abs(values).max(axis=2))
    clip = saturation_level_dn_s(store.attrs())
    sat = saturated_mask(store, level, bands, clip, origin) if clip is not None else np.zeros_like(clipped)
    sun = recovered_sun_mask(store.attrs(), level, sat.shape, origin, tuple(store.shapes[0]))
    mask = np.where(sat, 255, np.where(sun, 64, np.where(clipped, 128, 0))).astype(np.uint8)
    path = output.with_name(f"{output.stem}_saturated.png")
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), mask):
            raise ConfigurationError(f"{path}: OpenCV cannot write the saturation mask")
    out = {"mask": str(path), "saturated_px": int(sat.sum()), "recovered_sun_px": int((sun & ~sat).sum()),
           "clipped_estimate_px": int((clipped & ~sat & ~sun).sum()),
           "known": clip is not None, "level_dn_s": clip}
    if clip is None:
        out["reason"] = "the product has no rig snapshot saying where clipping starts: only clipped estimates marked"
    return out
