"""The applications' part of the demo: a rendered mirror ball and a relit preview of the demo's product.

Small on purpose (the whole demo stays within its time budget): the mirror ball at 128 × 128 px, 16 spp,
on a 10 nm grid (31 wavelengths, 11 Mitsuba passes); relighting to illuminant A from the ColorChecker's
white patch, whose direction and reflectance the simulated session's ground truth gives.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path


def demo_applications(product: str | Path, out: str | Path, session: str | Path | None = None,
                      progress: Callable[[str], None] | None = None) -> dict:
    """Render the mirror ball and relight the product (when the session knows its white patch); returns the files."""
    from omnispectral.apps.relight import WhiteReference, relight_product
    from omnispectral.apps.render import render_product

    out = Path(out)
    files: dict = {}
    ball = render_product(product, out / "render_mirror_ball", width=128, height=128, spp=16, wavelength_step_nm=10.0,
                          progress=progress)
    files["render_mirror_ball"] = ball["files"]["png"]
    files["render_mirror_ball_spectral"] = ball["files"]["spectral_exr"]
    gt = Path(session) / "ground_truth" / "ground_truth.json" if session else None
    if gt is not None and gt.is_file():
        patches = json.loads(gt.read_text()).get("colorchecker_patches") or []
        white = next((p for p in patches if p["name"].startswith("white")), None)
        if white is not None:
            ref = WhiteReference(white["lon_deg"], white["lat_deg"], 0.6 * white["half_size_deg"])
            rel = relight_product(product, out / "relit_A", [ref], to="A",
                                  reflectance=(white["wavelength_nm"], white["reflectance"]), progress=progress)
            files["relit_preview"] = rel["previews"]["relit"]
            files["relit_product"] = rel["output"]
    return files
