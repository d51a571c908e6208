"""``omnispectral view``: the arguments; run by :mod:`omnispectral.cli.view`."""

from __future__ import annotations

__all__ = ["add_commands"]


def add_commands(sub) -> None:
    """Register ``view``."""
    v = sub.add_parser("view", help="look around a product in the browser, probe spectra, scrub a time-lapse",
                       description="A read-only local web server showing the panorama in a 360° viewer (tiles "
                                   "tone-mapped on demand: colour, one band, spectral uncertainty; exposure), the "
                                   "spectrum at a clicked direction (estimate ± 2σ, CIE xy, six bands; shift-click "
                                   "compares a second one; CSV export) and, for a series from process-series, a "
                                   "time slider with the probed spectrum over the day.")
    v.add_argument("product", metavar="PRODUCT|SERIES", help="product directory or process-series output")
    v.add_argument("--port", type=int, default=8000,
                   help="TCP port, 0..65535 (default 8000; 0: any free port, printed when ready)")
    v.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1, this machine only; others print a warning)")
    v.add_argument("--open", action="store_true", help="open the viewer in the default web browser")
    v.set_defaults(func="omnispectral.cli.view:cmd_view")
