"""``omnispectral view``: the 360° spectral viewer of a product or a processed time-lapse series."""

from __future__ import annotations

from rich.markup import escape

from omnispectral.cli._common import console, err_console
from omnispectral.view.server import LOCAL_HOSTS, check_listen_address, check_port_number, serve, view_slots

__all__ = ["cmd_view"]


def cmd_view(args) -> int:
    check_port_number(args.port)  # a usage error before anything is printed or opened
    if args.host not in LOCAL_HOSTS:
        err_console.print(f"[bold yellow]warning:[/bold yellow] serving on {escape(args.host)}: anyone who can reach "
                          f"this machine on port {args.port} can look at the product (read-only). The default is "
                          "127.0.0.1.")
    check_listen_address(args.host, args.port)  # a busy port: one error line, not the product opened first
    view_slots(args.product)  # not a product or series: one error line before anything else is printed
    err_console.print(f"opening {escape(str(args.product))} (fitting its estimator takes a few seconds)…")

    def ready(url: str) -> None:
        console.print(f"Viewer of {args.product} at [bold]{url}[/bold] (Ctrl-C to stop)")

    serve(args.product, host=args.host, port=args.port, open_browser=args.open, on_ready=ready)
    return 0
