"""Which accuracy limits apply to a run: a product whose accuracy falls far from what its settings can reach says so.

``process`` records the result in ``product.json`` (``accuracy_warnings``), the report shows it and the command
line prints each as one line at the end.  Each limit is decided from what a real run knows: the rig (its
cameras, raw settings, baseline), the run's settings (the registration, the calibration used) and the session's
own measurements (the registration's statistics) — never from a simulation's ground truth.  Each warning is one
sentence: what is off, how much to expect (its order of magnitude, with the docs/benchmarks.md section that
measured it) and what to do.

The limits (:func:`accuracy_warnings`):

``bayer``
    Raw Bayer frames (``[cameras.X.raw]``).  A 2 × 2 colour filter array samples red and blue once per 2 × 2
    photosites and green twice, so a demosaiced pixel's colour is interpolated from neighbours up to ~2 px
    away (Menon 2007's directional filters span 5 photosites).  Colour detail narrower than two CFA periods,
    :data:`BAYER_MIN_FEATURE_PX` = 4 px, takes its neighbours' colours.  The rule: the angle 4 px subtend at
    the coarsest Bayer camera's centre (its pixels per degree from the camera model's focal length) is larger
    than :data:`TARGET_FEATURE_DEG`, the size of a colour target's patch at a working distance (a ColorChecker
    Classic's ~40 mm patch 2.3 m away; the simulated scene's 50 mm patches at 2.5 m are 1.15°).  The ``small``
    preset (2.6 px per degree: 4 px = 1.5°) warns — its default chart's patches are ~3 px and come out tens of
    ΔE*ab off against ~1 with RGB frames; ``paper-timelapse`` (21 px per degree: 4 px = 0.19°) does not.
``paper-registration``
    ``--registration paper``: one POC offset per direction (Sec. 4.3).  For content at infinity the A-to-B
    relation does not depend on the head's direction, so every direction's offset would be the same (B's
    mounting error) up to POC's few hundredths of a pixel.  The spread of the measured offsets (largest
    distance of a direction's offset from their median, directions that kept the calibrated offset left out)
    is therefore the parallax of the near content that dominated some directions; since a direction holds
    near and far content together, one offset leaves the rest of it off by about that much.  The rule: spread
    above :data:`PAPER_PARALLAX_PX` (1 px: a B image one pixel off its A image gives a 4-px colour target a
    quarter of its neighbours' signal in B's bands).  The content's distance is about ``|b| f_B / spread``
    (``b`` the baseline, ``f_B`` B's focal length in px): on the ``small`` rig the ground 1.5 m below the head
    spreads them by ~5 px, an HDR panorama at infinity by 0.4 px.  The per-pixel parallax (``--registration
    parallax``, the default) follows it.
``session-yaw``
    Camera B's mounting fitted from a session's own images (``rig_calibration.method == "scene"``, this
    session's or a file's).  Along the epipolar lines a yaw change and a common inverse depth are the same
    shift, so the fit puts the farthest dense cluster of blocks (its ``far_anchor``) at infinity
    (:mod:`omnispectral.product.rigfit`); the yaw is then off by that content's true parallax angle, ``b / Z``
    for content ``Z`` metres away, and the per-direction figures of :mod:`omnispectral.product.far_content`
    (measured against the same anchor) cannot see it.  Content at infinity (sky, the horizon, distant land)
    surrounds the rig; a plane at distance ``Z`` lies within a half-turn of pan, and only the part of it whose
    parallax stays within the anchor's window (a fraction of a pixel) joins the cluster.  The rule: the anchor
    holds fewer than :data:`ANCHOR_MIN_BLOCKS` blocks (the fit kept the rig file's yaw) or its directions
    span less than :data:`ANCHOR_MIN_SPAN_DEG` of pan (the plan's pan of each anchor direction; 360° minus the
    largest gap between them): it may be one surface, e.g. a room's far wall, and the yaw is off by ``b / Z``,
    stated for a surface :data:`NEAR_ANCHOR_M` away (0.34–1.1° on a 60-mm baseline; an indoor session on the
    ``small`` rig: 0.9° off, 2.5 px at infinity).  A chessboard fit states its own uncertainty at infinity,
    which :func:`omnispectral.product.far_content.far_content_warning` reports.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from omnispectral.capture.session import Session
from omnispectral.errors import OmnispectralError
from omnispectral.rig import Rig

__all__ = ["ANCHOR_MIN_BLOCKS", "ANCHOR_MIN_SPAN_DEG", "BAYER_MIN_FEATURE_PX", "NEAR_ANCHOR_M", "PAPER_PARALLAX_PX",
           "TARGET_FEATURE_DEG", "accuracy_warnings", "anchor_span_deg", "bayer_warning", "paper_registration_warning",
           "product_accuracy_warnings", "session_yaw_warning"]

#: Colour detail narrower than this (px, two periods of a 2 × 2 colour filter array) mixes with its neighbours
#: when demosaiced.
BAYER_MIN_FEATURE_PX = 4.0
#: Angular size (deg) of a colour target's patch at a working distance: a ColorChecker Classic's ~40 mm patch
#: 2.3 m away.
TARGET_FEATURE_DEG = 1.0
#: Spread (px) of the paper registration's per-direction offsets beyond which near content is misregistered.
PAPER_PARALLAX_PX = 1.0
#: A session fit's far anchor with fewer blocks did not fix the yaw (``product.rigfile``: the rig file's is kept).
ANCHOR_MIN_BLOCKS = 5
#: A far anchor whose directions span less pan than this (deg) may be one surface at a finite distance.
ANCHOR_MIN_SPAN_DEG = 180.0
#: Distances (m) of the farthest surface of an enclosed space (a room, a courtyard) for the yaw's stated error.
NEAR_ANCHOR_M = (3.0, 10.0)


def _warning(kind: str, message: str, **figures) -> dict:
    return {"kind": kind, "message": message, "figures": figures}


def bayer_warning(rig: Rig) -> dict | None:
    """The ``bayer`` limit (module docstring) for a rig, or ``None``.

    Parameters
    ----------
    rig
        The session's rig (its cameras' ``raw`` settings and models).

    Returns
    -------
    dict or None
        ``{"kind": "bayer", "message": ..., "figures": {...}}`` when colour detail of
        :data:`TARGET_FEATURE_DEG` is below :data:`BAYER_MIN_FEATURE_PX` on a Bayer camera.
    """
    bayer = [c for c in rig.camera_names if rig.cameras[c].raw is not None]
    if not bayer:
        return None
    px_per_deg = min(float(np.radians(rig.camera_model(c).fx)) for c in bayer)
    feature_deg = BAYER_MIN_FEATURE_PX / px_per_deg
    if feature_deg <= TARGET_FEATURE_DEG:
        return None
    cams = " and ".join(bayer)
    return _warning(
        "bayer",
        f"Raw Bayer frames on camera {cams} at {px_per_deg:.1f} px per degree: colour detail under {feature_deg:.1f}° "
        f"({BAYER_MIN_FEATURE_PX:g} px, two periods of the 2×2 colour filter array) takes its neighbours' colours "
        f"when demosaiced, so small colour targets (a {TARGET_FEATURE_DEG:g}° chart patch is "
        f"{TARGET_FEATURE_DEG * px_per_deg:.1f} px) may be off by tens of ΔE*ab instead of ~1 (docs/benchmarks.md, "
        f"Raw Bayer frames); record RGB frames, or use a sensor or lens with more pixels per degree (or bring the "
        f"targets closer) so each patch spans {BAYER_MIN_FEATURE_PX:g} px or more.",
        cameras=bayer, px_per_deg=px_per_deg, min_feature_px=BAYER_MIN_FEATURE_PX, min_feature_deg=feature_deg,
        target_deg=TARGET_FEATURE_DEG)


def _baseline_m(index: dict, rig: Rig) -> float:
    """|b| (m): the calibrated mounting's baseline when the product has one, else the rig file's."""
    cal = (index.get("registration") or {}).get("rig_calibration") or {}
    mm = (cal.get("camera_b_mounting") or {}).get("baseline_mm") or rig.mounting.baseline_mm
    return float(np.linalg.norm(np.asarray(mm, np.float64))) / 1000.0


def paper_registration_warning(index: dict, rig: Rig) -> dict | None:
    """The ``paper-registration`` limit (module docstring), or ``None``.

    Parameters
    ----------
    index
        The product's index (``registration.method == "paper"`` and its ``directions``' offsets).
    rig
        The session's rig (camera B's focal length, the baseline).

    Returns
    -------
    dict or None
        The warning when the measured offsets spread beyond :data:`PAPER_PARALLAX_PX`.
    """
    reg = index.get("registration") or {}
    if reg.get("method") != "paper" or "B" not in rig.camera_names:
        return None
    offsets = np.array([(a["offset_dx_px"], a["offset_dy_px"]) for a in reg.get("directions", [])
                        if not a.get("used_fallback")], np.float64).reshape(-1, 2)
    offsets = offsets[np.isfinite(offsets).all(axis=1)]
    if offsets.shape[0] < 3:
        return None
    spread = float(np.max(np.linalg.norm(offsets - np.median(offsets, axis=0), axis=1)))
    if spread <= PAPER_PARALLAX_PX:
        return None
    distance_m = _baseline_m(index, rig) * rig.camera_model("B").fx / spread
    return _warning(
        "paper-registration",
        f"--registration paper: the directions' offsets of camera B differ by up to {spread:.1f} px, the parallax "
        f"of content about {distance_m:.1f} m away or nearer, which one offset per direction cannot follow, so near "
        f"content is misregistered between the cameras by up to that much (band PSNR 2-12 dB below the default "
        f"path's and the ColorChecker bounds missed in the registration matrix: docs/benchmarks.md, Registration "
        f"across conditions); use --registration parallax (the default).",
        spread_px=spread, bound_px=PAPER_PARALLAX_PX, distance_m=distance_m, n_measured=int(offsets.shape[0]))


def anchor_span_deg(pans_deg) -> float:
    """The pan a set of directions spans (deg): 360° minus the largest gap between their distinct pans (0 for one).

    Parameters
    ----------
    pans_deg
        The directions' pan angles (deg).

    Returns
    -------
    float
        The span in degrees, 0-360.
    """
    p = np.unique(np.round(np.mod(np.asarray(list(pans_deg), np.float64), 360.0), 6))
    if p.size < 2:
        return 0.0
    gaps = np.diff(np.concatenate([p, [p[0] + 360.0]]))
    return float(360.0 - gaps.max())


def session_yaw_warning(index: dict, rig: Rig, pans_deg: Mapping[int, float] | None = None) -> dict | None:
    """The ``session-yaw`` limit (module docstring), or ``None``.

    Parameters
    ----------
    index
        The product's index (``registration.rig_calibration`` with ``method`` and ``far_anchor``,
        ``registration.rig_calibration_source``).
    rig
        The session's rig (camera B's focal length, the baseline).
    pans_deg
        The plan's pan per direction index (deg); without it only the anchor's block count is judged.

    Returns
    -------
    dict or None
        The warning when the far anchor holds fewer than :data:`ANCHOR_MIN_BLOCKS` blocks or spans less than
        :data:`ANCHOR_MIN_SPAN_DEG` of pan.
    """
    reg = index.get("registration") or {}
    cal = reg.get("rig_calibration") or {}
    if reg.get("method") != "parallax" or not cal or cal.get("method", "scene") != "scene":
        return None
    anchor = cal.get("far_anchor") or {}
    n = int(anchor.get("n_blocks", 0))
    dirs = [int(d) for d in anchor.get("directions", [])]
    span = anchor_span_deg([pans_deg[d] for d in dirs if d in pans_deg]) if pans_deg is not None and dirs else None
    if n >= ANCHOR_MIN_BLOCKS and (span is None or span >= ANCHOR_MIN_SPAN_DEG):
        return None
    base = _baseline_m(index, rig)
    fx = rig.camera_model("B").fx
    deg = [float(np.degrees(base / z)) for z in reversed(NEAR_ANCHOR_M)]
    px = [float(np.radians(d) * fx) for d in deg]
    source = (reg.get("rig_calibration_source") or {}).get("kind")
    whose = "this session's own images" if source in (None, "session") else "a session's own images (the file)"
    if n < ANCHOR_MIN_BLOCKS:
        what = (f"Camera B's yaw could not be fixed from {whose}: only {n} far blocks, so the rig file's yaw was "
                f"kept, off by as much as the mounting was mis-measured")
    else:
        where = f"{len(dirs)} direction{'s' if len(dirs) != 1 else ''} within {span:.0f}° of pan"
        what = (f"Camera B's yaw was fitted from {whose} and anchored on {n} far blocks in {where}, perhaps one "
                f"surface rather than the horizon")
    return _warning(
        "session-yaw",
        f"{what}: the yaw is then off by that content's parallax, {deg[0]:.1f}-{deg[1]:.1f}° ({px[0]:.1f}-"
        f"{px[1]:.1f} px at infinity) for a surface {NEAR_ANCHOR_M[0]:g}-{NEAR_ANCHOR_M[1]:g} m away, which the "
        f"far-content figures (measured against the same anchor) do not include (docs/benchmarks.md, Calibration "
        f"views: chessboard views fix it to ~0.02 px); record calibration views: omnispectral capture "
        f"calibration-views -o SESSION (or pass --rig-calibration FILE of a chessboard fit).",
        anchor_blocks=n, anchor_directions=dirs, anchor_span_deg=span, min_blocks=ANCHOR_MIN_BLOCKS,
        min_span_deg=ANCHOR_MIN_SPAN_DEG, yaw_error_deg=deg, error_at_infinity_px=px, surface_m=list(NEAR_ANCHOR_M))


def accuracy_warnings(index: dict, rig: Rig, pans_deg: Mapping[int, float] | None = None) -> list[dict]:
    """Every accuracy limit that applies to a product (module docstring), in the order bayer, paper
    registration, session yaw.

    Parameters
    ----------
    index
        The product's index (``product.json``).
    rig
        The session's rig.
    pans_deg
        The plan's pan per direction index (deg), for the session fit's anchor.

    Returns
    -------
    list of dict
        ``{"kind", "message", "figures"}`` per limit; empty when none applies.
    """
    found = (bayer_warning(rig), paper_registration_warning(index, rig), session_yaw_warning(index, rig, pans_deg))
    return [w for w in found if w is not None]


def product_accuracy_warnings(index: dict) -> list[dict]:
    """A product's accuracy warnings: those its index records, else decided now from its session's rig and plan
    (products made before they were recorded); empty when the session cannot be opened.

    Parameters
    ----------
    index
        The product's index (``product.json``).

    Returns
    -------
    list of dict
        As :func:`accuracy_warnings`.
    """
    if "accuracy_warnings" in index:
        return list(index["accuracy_warnings"])
    try:
        session = Session.open(index["session"])
        rig, plan = session.rig(), session.plan()
    except (OmnispectralError, OSError, KeyError):
        return []
    return accuracy_warnings(index, rig, {d.index: d.pan_deg for d in plan.directions})
