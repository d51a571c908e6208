"""How the saturated sun is recovered: the methods in order of preference, and the choice among them.

- ``nd-bracket`` (:mod:`omnispectral.product.sun`): the attenuated bracket the capture aimed at the sun,
  a measurement;
- ``diffuse-reference`` (:mod:`omnispectral.product.sun_reference`): a white or grey target in the scene
  lit by the sun, whose direction the user gives, a measurement;
- ``sky-model`` (:mod:`omnispectral.product.sun_sky_model`): a published clear-sky model fitted to the
  panorama's sky, a model estimate;
- ``none``: the sun's pixels keep the shortest exposure's value, a lower bound, and every consumer says so.

``auto`` takes the first that recovers the sun.
"""

from __future__ import annotations

from omnispectral.errors import ConfigurationError
from omnispectral.imaging.geometry import CameraModel
from omnispectral.product.saturation import saturation_level_dn_s
from omnispectral.product.sun import (
    clipped_sun_direction,
    recover_sun_nd,
    refine_clipped_direction,
    sun_lower_bound_note,
)
from omnispectral.product.sun_reference import SunReference, recover_sun_reference
from omnispectral.product.sun_sky_model import recover_sun_sky_model

#: Methods of :func:`recover_sun`: ``auto`` and the methods in order of preference.
SUN_METHODS = ("auto", "nd-bracket", "diffuse-reference", "sky-model", "none")


def recover_sun(session, models: dict[str, CameraModel], rig, band_names: list[str], method: str = "auto",
                progress=None, store=None, reference: SunReference | None = None, merged=None) -> dict:
    """The sun by ``method``; ``auto`` takes the attenuated bracket when the session has one, else the diffuse
    ``reference`` when one is given, else the clear-sky model fitted to the panorama's sky (``store``, unpainted;
    a model estimate), else keeps the lower bound.  The last two find the clipped sun in the panorama, its
    direction refined on the ``merged`` directions when given (:func:`refine_clipped_direction`).

    Always returns a record: ``recovered`` says whether the panorama can hold the sun, ``method`` how.
    """
    if method not in SUN_METHODS:
        raise ConfigurationError(f"sun method must be one of {', '.join(SUN_METHODS)}, got {method!r}")
    tried = []
    if method in ("auto", "nd-bracket"):
        record = recover_sun_nd(session, models, rig.system(), band_names, progress)
        if record is not None and (record.get("recovered") or method == "nd-bracket"):
            return record
        tried.append(record["note"] if record else "no attenuated sun bracket in the session")
    clipped = None
    if store is not None and method in ("auto", "diffuse-reference", "sky-model"):
        clipped = clipped_sun_direction(store)
        level = saturation_level_dn_s(store.attrs())
        if clipped is not None and merged is not None and level is not None:
            clipped = refine_clipped_direction(clipped, merged, level)
    if method == "diffuse-reference" and (reference is None or store is None):
        raise ConfigurationError("--sun diffuse-reference needs --sun-reference LON,LAT (where the target is)")
    if method in ("auto", "diffuse-reference") and reference is not None and store is not None:
        record = recover_sun_reference(store, rig.system(), band_names, reference, clipped=clipped)
        if record.get("recovered") or method == "diffuse-reference":
            return record
        tried.append(record.get("note", "the diffuse reference gave no sun"))
    if method in ("auto", "sky-model") and store is not None:
        record = recover_sun_sky_model(store, rig.system(), band_names, clipped=clipped)
        if record.get("recovered") or method == "sky-model":
            return record
        tried.append(record.get("note", "the sky model did not fit"))
    if method == "nd-bracket":
        return {"method": "nd-bracket", "recovered": False,
                "note": "the session has no attenuated sun bracket (a rig without a [sun] table, or the "
                        "sun never clipped)"}
    return {"method": "none", "recovered": False,
            "note": sun_lower_bound_note() + (f" (tried: {'; '.join(tried)})" if tried else "")}
