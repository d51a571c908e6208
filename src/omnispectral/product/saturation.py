"""Which pixels of a product were saturated in every exposure (the sun): a lower bound, not a measurement.

Pixels that hold the recovered sun (:mod:`omnispectral.product.sun`, listed in the store's attributes
``omnispectral.sun.pixels``) are measurements again and are not counted as saturated.

The product stores no per-pixel saturation flags; the HDR merge (``imaging.hdr``, paper Sec. 4.1) leaves
pixels clipped in every exposure at the shortest exposure's value.  Their clipping level is known from the
rig snapshot in the panorama store (``0.99 · max_dn / t_shortest``), so a pixel of a pyramid level counts as
saturated when any level-0 pixel under it reaches ``SATURATION_FRACTION`` of that level.  Used by the
spectral EXR export (mask written beside it) and the environment maps of ``apps``.
"""

from __future__ import annotations

import tomllib

import numpy as np

from omnispectral.rig import rig_from_dict

__all__ = ["SATURATION_FRACTION", "clipped_mask", "recovered_sun_mask", "saturated_mask", "saturation_level_dn_s"]

#: A level-0 pixel counts as saturated from this fraction of the shortest exposure's clipping level.
SATURATION_FRACTION = 0.95


def saturation_level_dn_s(attrs: dict) -> float | None:
    """The shortest exposure's clipping level (DN/s) from the store's rig snapshot, or ``None``."""

    text = ((attrs.get("omnispectral") or {}).get("rig") or {}).get("toml")
    if not text:
        return None
    try:
        rig = rig_from_dict(tomllib.loads(text), "panorama rig snapshot", text)
    except Exception:  # a snapshot this version cannot read: no saturation information, said in describe()
        return None
    return 0.99 * rig.camera_a.max_dn / min(rig.bracket.exposures_s)


def recovered_sun_mask(attrs: dict, level: int, shape: tuple[int, int], origin: tuple[int, int] = (0, 0),
                       level0_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Pixels of a ``shape`` window (top-left ``origin`` at ``level``) over a level-0 pixel painted with the
    recovered sun (the store's ``omnispectral.sun.pixels``); all False when the sun was not recovered."""
    out = np.zeros(shape, bool)
    sun = (attrs.get("omnispectral") or {}).get("sun") or {}
    pix = sun.get("pixels") if sun.get("recovered") else None
    if not pix:
        return out
    mask = np.asarray(pix["mask"], bool)
    rows, cols = np.nonzero(mask)
    f = 2 ** level
    r = (rows + int(pix["row0"])) // f - origin[0]
    width0 = level0_shape[1] if level0_shape is not None else None
    c_abs = cols + int(pix["col0"])
    if width0:
        c_abs %= width0
    c = c_abs // f - origin[1]
    keep = (r >= 0) & (r < shape[0]) & (c >= 0) & (c < shape[1])
    out[r[keep], c[keep]] = True
    return out


def saturated_mask(store, level: int, bands: np.ndarray, level_dn_s: float,
                   origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """:func:`clipped_mask` without the pixels that hold the recovered sun (:func:`recovered_sun_mask`)."""
    sat = clipped_mask(store, level, bands, level_dn_s, origin)
    if sat.any():
        sat &= ~recovered_sun_mask(store.attrs(), level, sat.shape, origin, tuple(store.shapes[0]))
    return sat


def clipped_mask(store, level: int, bands: np.ndarray, level_dn_s: float,
                 origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Pixels of ``level`` over at least one level-0 pixel at ≥ ``SATURATION_FRACTION`` of ``level_dn_s``.

    ``bands`` is the level's window whose top-left pixel is ``origin`` (row, col).  A level-``L`` pixel is a
    mean of ``4^L`` level-0 pixels, so only those at ≥ threshold/4^L can hold one; their level-0 footprints
    are read row by row.
    """
    thr = SATURATION_FRACTION * level_dn_s
    f = 2 ** level
    peak = np.nan_to_num(bands, nan=0.0).max(axis=2)
    cand = peak >= thr / (f * f)
    if level == 0 or not cand.any():
        return peak >= thr if level == 0 else cand
    out = np.zeros_like(cand)
    h0, w0 = store.shapes[0]
    o_r, o_c = origin
    for r in np.flatnonzero(cand.any(axis=1)):
        cols = np.flatnonzero(cand[r])
        c0, c1 = int(cols.min()), int(cols.max()) + 1
        full = store.read(0, slice((o_r + r) * f, min(h0, (o_r + r + 1) * f)),
                          slice((o_c + c0) * f, min(w0, (o_c + c1) * f)))
        hit = np.nan_to_num(full, nan=0.0).max(axis=2) >= thr
        pad = np.zeros((f, (c1 - c0) * f), bool)
        pad[:hit.shape[0], :hit.shape[1]] = hit
        out[r, c0:c1] = pad.reshape(f, c1 - c0, f).any(axis=(0, 2)) & cand[r, c0:c1]
    return out
