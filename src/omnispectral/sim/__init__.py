"""The simulator: everything that stands in for the world and the hardware, and the truth it knows.

- :mod:`~omnispectral.sim.scenes`: spectral scenes (procedural outdoor and indoor, HDR panoramas, reflectance
  cubes, a chessboard) under a daylight sky with an analytic sun.
- :mod:`~omnispectral.sim.simulate`: the rig's cameras rendering a scene (optics, sensor noise, filters, the
  unknown mounting of camera B) and a whole simulated session through the real capture loop.
- :mod:`~omnispectral.sim.truth`: the ground truth a simulation writes beside its session, and its reader.
- :mod:`~omnispectral.sim.devices`: simulated head, cameras, filter changer and clock, with fault injection.
- :mod:`~omnispectral.sim.emulators`: the pan/tilt heads' serial protocols emulated on pseudo-terminals.
- :mod:`~omnispectral.sim.boardviews`: chessboard calibration views; :mod:`~omnispectral.sim.photographs`:
  photographs as a consumer camera would take them; :mod:`~omnispectral.sim.synthetic`: merged directions
  made directly from a panorama (mosaic tests and benchmarks).

Processing never imports this package (``tests/test_architecture.py``): what a real rig would not know, the
pipeline measures or estimates.
"""
