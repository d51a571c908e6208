"""A scene by name, as the command line and the demo ask for one: ``procedural``, an HDR panorama file, a cube."""

from __future__ import annotations

import datetime as _dt

from omnispectral.choices import DEFAULT_DATE
from omnispectral.errors import ConfigurationError
from omnispectral.sim.scenes.cube import CubeOnWallScene
from omnispectral.sim.scenes.indoor import IndoorScene
from omnispectral.sim.scenes.panorama import PanoramaScene
from omnispectral.sim.scenes.procedural import ProceduralOutdoorScene

__all__ = ["DEFAULT_DATE", "build_scene"]


def build_scene(scene: str, cube: str | None, when: _dt.datetime, wavelength_nm=None, seed: int = 0,
                chart_distance_m: float | None = None, chart_patch_m: float | None = None, light: str | None = None):
    """``procedural`` (sun and sky at ``when``), ``indoor`` (a room lit by ``light``), or an HDR
    equirectangular panorama file; with ``cube``, a hyperspectral reflectance cube mounted on a wall of
    the procedural scene (or the indoor room's painting)."""
    kwargs = {} if wavelength_nm is None else {"wavelength_nm": wavelength_nm}
    if scene == "indoor":  # the cube, if any, is the room's painting
        return IndoorScene(light or "FL11", painting=cube or None, **kwargs)
    if light:
        raise ConfigurationError("--light chooses the light source of --scene indoor")
    if scene == "procedural":
        chart = {k: v for k, v in (("chart_distance_m", chart_distance_m), ("chart_patch_m", chart_patch_m))
                 if v is not None}
        base = ProceduralOutdoorScene(time_hhmm=f"{when:%H:%M}", day_of_year=when.timetuple().tm_yday,
                                      seed=seed, **chart, **kwargs)
    else:
        if cube:
            raise ConfigurationError("--cube mounts the cube on a wall of the procedural or the indoor scene")
        return PanoramaScene(scene, **kwargs)
    return CubeOnWallScene(cube, base=base) if cube else base
