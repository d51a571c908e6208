"""``omnispectral view``: the 360° spectral viewer of a product or a processed time-lapse series."""

from __future__ import annotations

from rich.markup import escape

from omnispectral.cli._common import console, err_console
from omnispectral.view.server import LOCAL_HOSTS, check_listen_address, check_port_number, serve


def cmd_view(args) -> int:
    check_port_number(args.port)  # a usage error before anything is printed or opened
    if args.host not in LOCAL_HOSTS:
        err_console.print(f"[bold yellow]warning:[/bold yellow] serving on {escape(args.host)}: anyone who can reach "
                          f"this machine on port {args.port} can look at the product (read-only). The default is "
                          "127.0.0.1.")
    check_listen_address(args.host, args.port)  # a busy port: one error line, not the product opened first
    err_console.print(f"opening {escape(str(args.product))} (fitting its estimator takes a few seconds)…")

    def ready(url: str) -> None:
        console.print(f"Viewer of {args.product} at [bold]{url}[/bold] (Ctrl-C to stop)")

    serve(args.product, host=args.host, port=args.port, open_browser=args.open, on_ready=ready)
    return 0


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
    v.set_defaults(func=cmd_view)
