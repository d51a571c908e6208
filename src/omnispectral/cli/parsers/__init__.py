"""The command line's argument parsers: one light module per area, importing only argparse, the standard library,
:mod:`omnispectral.errors` and :mod:`omnispectral.choices` (names and defaults the library owns), never NumPy,
colour-science, OpenCV, SciPy or Zarr, so ``omnispectral --help`` and ``omnispectral COMMAND --help`` answer at once.

Each module's ``add_commands(subparsers)`` registers its commands, and each command's ``func`` default names the
function that runs it as ``"omnispectral.cli.AREA:cmd_NAME"``; :func:`omnispectral.cli.main` imports that module (and
with it the library) only when the command runs.
"""
