"""Scenes of the simulated rig: the demo, the test bed and the ground truth.

- :class:`ProceduralOutdoorScene`: clear sky and HDR sun following the time of day, ground,
  buildings with measured reflectances, a ColorChecker, an optional near object (parallax).
- :class:`PanoramaScene`: any HDR RGB equirectangular panorama, spectrally up-sampled (Mallett & Yuksel 2019).
- :class:`CubeOnWallScene`: a hyperspectral reflectance cube on a wall of the procedural scene.

All share the :class:`Scene` interface: ``spectral_radiance``, the fast ``band_radiance``,
``describe``, ``colorchecker_patches`` and equirectangular ground truth.
:func:`build_scene` makes one by name (the command line's ``--scene`` and ``--cube``).
"""

from omnispectral.sim.scenes.base import (
    Scene,
    direction_to_lonlat,
    equirect_directions,
    equirect_lonlat,
    lonlat_to_direction,
)
from omnispectral.sim.scenes.build import DEFAULT_DATE, build_scene
from omnispectral.sim.scenes.cube import CubeOnWallScene, load_reflectance_cube
from omnispectral.sim.scenes.indoor import IndoorScene
from omnispectral.sim.scenes.panorama import PanoramaScene, read_panorama
from omnispectral.sim.scenes.procedural import ProceduralOutdoorScene
from omnispectral.sim.scenes.sky import ClearSkyDaylight, SolarPosition, solar_position

__all__ = [
    "DEFAULT_DATE",
    "ClearSkyDaylight",
    "CubeOnWallScene",
    "IndoorScene",
    "PanoramaScene",
    "ProceduralOutdoorScene",
    "Scene",
    "SolarPosition",
    "build_scene",
    "direction_to_lonlat",
    "equirect_directions",
    "equirect_lonlat",
    "load_reflectance_cube",
    "lonlat_to_direction",
    "read_panorama",
    "solar_position",
]
