"""How the saturated sun is recovered: the methods in order of preference, and the choice among them.

- ``nd-bracket`` (:mod:`omnispectral.product.sun`): the attenuated bracket the capture aimed at the sun,
  a measurement;
- ``diffuse-reference`` (:mod:`omnispectral.product.sun_reference`): a white or grey target in the scene
  lit by the sun, whose direction the user gives, a measurement;
- ``sky-model`` (:mod:`omnispectral.product.sun_sky_model`): a published clear-sky model fitted to the
  panorama's sky, a model estimate;
- ``none``: the sun's pixels keep the shortest exposure's value, a lower bound, and every consumer says so.

``auto`` takes the first that recovers the sun.  :data:`SUN_METHODS` maps each name to its function (the valid
names are its keys).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from omnispectral.choices import SUN_METHOD_NAMES, method_from
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
from omnispectral.progress import ProgressCallback

__all__ = ["SUN_METHODS", "SunInputs", "recover_sun", "sun_method"]


@dataclass
class SunInputs:
    """What the sun's recovery may use: the session (its attenuated bracket), the camera models, the rig, the
    bands, the unpainted panorama ``store`` and the ``merged`` directions (for the clipped sun's direction),
    the diffuse ``reference`` and the progress callback (stage ``"sun"``)."""

    session: object
    models: dict[str, CameraModel]
    rig: object
    band_names: list[str]
    progress: ProgressCallback | None = None
    store: object = None
    reference: SunReference | None = None
    merged: object = None
    _clipped: list = field(default_factory=list, init=False, repr=False)

    def clipped(self):
        """The clipped sun's direction in the panorama, refined on the merged directions when given
        (:func:`~omnispectral.product.sun.refine_clipped_direction`); found once.  Needs ``store``."""
        if not self._clipped:
            clipped = clipped_sun_direction(self.store)
            level = saturation_level_dn_s(self.store.attrs())
            if clipped is not None and self.merged is not None and level is not None:
                clipped = refine_clipped_direction(clipped, self.merged, level)
            self._clipped.append(clipped)
        return self._clipped[0]


#: ``attempt(inputs, tried, chosen) -> record or None``: ``chosen`` says the user asked for this method (its record
#: is returned even when it did not recover the sun); ``None`` lets the next method try, with the reason appended
#: to ``tried``.
SunAttempt = Callable[[SunInputs, list, bool], dict | None]


def _nd_bracket(inputs: SunInputs, tried: list, chosen: bool) -> dict | None:
    """The attenuated bracket (:func:`~omnispectral.product.sun.recover_sun_nd`)."""
    record = recover_sun_nd(inputs.session, inputs.models, inputs.rig.system(), inputs.band_names, inputs.progress)
    if record is not None and (record.get("recovered") or chosen):
        return record
    if record is None and chosen:
        return {"method": "nd-bracket", "recovered": False,
                "note": "the session has no attenuated sun bracket (a rig without a [sun] table, or the "
                        "sun never clipped)"}
    tried.append(record["note"] if record else "no attenuated sun bracket in the session")
    return None


def _diffuse_reference(inputs: SunInputs, tried: list, chosen: bool) -> dict | None:
    """A white or grey target lit by the sun (:func:`~omnispectral.product.sun_reference.recover_sun_reference`)."""
    if inputs.reference is None or inputs.store is None:
        if chosen:
            raise ConfigurationError("--sun diffuse-reference needs --sun-reference LON,LAT (where the target is)")
        return None
    record = recover_sun_reference(inputs.store, inputs.rig.system(), inputs.band_names, inputs.reference,
                                   clipped=inputs.clipped())
    if record.get("recovered") or chosen:
        return record
    tried.append(record.get("note", "the diffuse reference gave no sun"))
    return None


def _sky_model(inputs: SunInputs, tried: list, chosen: bool) -> dict | None:
    """A clear-sky model fitted to the panorama's sky
    (:func:`~omnispectral.product.sun_sky_model.recover_sun_sky_model`)."""
    if inputs.store is None:
        return None
    record = recover_sun_sky_model(inputs.store, inputs.rig.system(), inputs.band_names, clipped=inputs.clipped())
    if record.get("recovered") or chosen:
        return record
    tried.append(record.get("note", "the sky model did not fit"))
    return None


def _none(inputs: SunInputs, tried: list, chosen: bool) -> dict | None:
    """Nothing recovered: the lower bound (:func:`recover_sun` records it)."""
    return None


#: The recovering methods in order of preference (what ``auto`` tries).
PREFERENCE: tuple[SunAttempt, ...] = (_nd_bracket, _diffuse_reference, _sky_model)


def _auto(inputs: SunInputs, tried: list, chosen: bool) -> dict | None:
    """The first method of :data:`PREFERENCE` that recovers the sun."""
    for attempt in PREFERENCE:
        record = attempt(inputs, tried, False)
        if record is not None:
            return record
    return None


#: The sun's recovery methods by name (the valid names are its keys): ``auto`` and the methods in order of
#: preference, then ``none``.
SUN_METHODS: dict[str, SunAttempt] = dict(zip(SUN_METHOD_NAMES, (_auto, _nd_bracket, _diffuse_reference, _sky_model,
                                                                _none), strict=True))


def sun_method(name: str) -> SunAttempt:
    """The recovery method called ``name``.

    Parameters
    ----------
    name
        A key of :data:`SUN_METHODS`.

    Returns
    -------
    SunAttempt
        The method's function.

    Raises
    ------
    ConfigurationError
        For an unknown name (the message lists the valid ones).
    """
    return method_from(SUN_METHODS, name, "sun method")


def recover_sun(session, models: dict[str, CameraModel], rig, band_names: list[str], method: str = "auto",
                progress: ProgressCallback | None = None, store=None, reference: SunReference | None = None,
                merged=None) -> dict:
    """The sun by ``method``; ``auto`` takes the attenuated bracket when the session has one, else the diffuse
    ``reference`` when one is given, else the clear-sky model fitted to the panorama's sky (``store``, unpainted;
    a model estimate), else keeps the lower bound.  The last two find the clipped sun in the panorama, its
    direction refined on the ``merged`` directions when given (:func:`refine_clipped_direction`).

    Parameters
    ----------
    session, models, rig, band_names
        The session, its camera models, its rig and the panorama's band names.
    method
        A key of :data:`SUN_METHODS`.
    progress
        ``progress("sun", done, total)`` over the attenuated bracket's directions, or ``None``.
    store, reference, merged
        The unpainted panorama, the diffuse reference and the merged directions, when there are.

    Returns
    -------
    dict
        Always a record: ``recovered`` says whether the panorama can hold the sun, ``method`` how.
    """
    attempt = sun_method(method)
    tried: list[str] = []
    record = attempt(SunInputs(session, models, rig, band_names, progress, store, reference, merged), tried, True)
    if record is not None:
        return record
    return {"method": "none", "recovered": False,
            "note": sun_lower_bound_note() + (f" (tried: {'; '.join(tried)})" if tried else "")}
