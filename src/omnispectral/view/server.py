"""The viewer's read-only web application (Starlette) and its server (uvicorn).

What a request can reach is fixed when the application is made: the product (or the products of a
time-lapse series) it was given, opened through :func:`omnispectral.product.layout.open_product`, and the
front-end files of ``view/static`` read into memory at start.  No part of a request path or query is ever
joined to a file-system path: static files are looked up by name in that in-memory table, tiles are
addressed by integers checked against the level's grid, and every parameter is parsed and range-checked
(a bad one is a 400 with a one-line JSON error, a direction the panorama does not cover a 422).

Routes::

    GET /                                index.html
    GET /static/NAME                     the viewer's script, stylesheet and vendored Photo Sphere Viewer
    GET /api/info                        slots, tile levels, bands, modes, wavelengths
    GET /api/tile/LEVEL/COL/ROW.png      an equirectangular tile (query: t, mode, band, ev)
    GET /api/base.png                    the whole panorama, 1024 × 512 (same query)
    GET /api/spectrum?lon=&lat=[&t=|&all=1]   what ``omnispectral spectrum --json`` prints, plus CIE xy
    GET /api/auto-exposure?lon=&lat=&fov=     exposure (EV) that fits the view
    GET /api/probes.csv?p=LON,LAT[&p=…]       the probed spectra as CSV

Rendering (and opening a slot's product the first time it is asked for) runs in worker threads, at most
``max_parallel`` at once (an AnyIO capacity limiter), so a burst
of requests queues instead of holding one window per request in memory; encoded tiles are kept in a
:class:`~omnispectral.view.tiles.TileCache`.
"""

from __future__ import annotations

import csv
import io
import math
import mimetypes
import re
import socket
import threading
import webbrowser
from dataclasses import dataclass
from pathlib import Path

import anyio
import numpy as np
from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from omnispectral.errors import ConfigurationError, InputFileError, OmnispectralError
from omnispectral.product.series import series_products
from omnispectral.product.spectra import spectrum_in_store
from omnispectral.view.tiles import MODES, Display, SlotRenderer, TileCache, encode_png, viewer_levels

__all__ = ["BASE_SIZE", "LOCAL_HOSTS", "PORT_RANGE", "STATIC_DIR", "TILE_PX", "BadRequest", "CannotListenError",
           "LoopbackHostMiddleware", "Slot", "ViewerState", "auto_exposure", "bad_request", "base", "bound_port",
           "check_listen_address", "check_port_number", "create_app", "damaged_product", "host_name", "host_port",
           "http_error", "index_page", "info", "load_static", "no_icon", "probes", "probes_csv", "serve", "spectrum",
           "static_file", "tile", "unprocessable", "view_slots"]

STATIC_DIR = Path(__file__).parent / "static"
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1", "[::1]")
BASE_SIZE = (1024, 512)
TILE_PX = 256
_INT = re.compile(r"^[0-9]{1,6}$")


class BadRequest(ConfigurationError):
    """A request parameter that is missing or malformed (HTTP 400)."""


class CannotListenError(OmnispectralError):
    """The server cannot listen on the address asked for (a port in use, an address not of this machine): the
    work failed (exit 1), the command line was not wrong."""


@dataclass(frozen=True)
class Slot:
    """One panorama the viewer serves: a label (time of day for a series) and its product directory."""

    label: str
    time: str | None
    product: Path


def view_slots(path: str | Path) -> tuple[str, list[Slot]]:
    """``("product", [slot])`` for a product directory, ``("series", slots)`` for ``process-series`` output."""
    path = Path(path)
    if (path / "product.json").is_file():
        return "product", [Slot(path.name, None, path)]
    if (path / "series_product.json").is_file():
        return "series", [Slot(t[11:16] or t, t, p) for t, p in series_products(path)]
    if not path.exists():
        raise InputFileError(path, "does not exist")
    raise InputFileError(path, "is neither a product (no product.json) nor a processed time-lapse series "
                               "(no series_product.json)")


def load_static(directory: Path = STATIC_DIR) -> dict[str, tuple[bytes, str]]:
    """Every file under ``directory`` by its relative POSIX name → (content, media type), read once."""
    table = {}
    for p in sorted(directory.rglob("*")):
        if p.is_file():
            name = p.relative_to(directory).as_posix()
            media = mimetypes.guess_type(name)[0] or "application/octet-stream"
            if name.endswith((".js", ".mjs")):
                media = "text/javascript"
            table[name] = (p.read_bytes(), media)
    return table


class ViewerState:
    """Everything the application serves: the slots' renderers (opened lazily), the tile cache, the limiter."""

    def __init__(self, path: str | Path, cache_bytes: int = 64 * 2**20, max_parallel: int = 2):
        self.kind, self.slots = view_slots(path)
        self.name = Path(path).resolve().name
        self._renderers: dict[int, SlotRenderer] = {}
        self._open_lock = threading.Lock()
        self.cache = TileCache(cache_bytes)
        self.max_parallel = max_parallel
        self.limiter: anyio.CapacityLimiter | None = None  # made inside the event loop (AnyIO requires it)
        first = self.renderer(0)
        self.levels = viewer_levels(first.shapes[0][1], TILE_PX)

    def renderer(self, t: int) -> SlotRenderer:
        with self._open_lock:
            if t not in self._renderers:
                self._renderers[t] = SlotRenderer(self.slots[t].product)
            return self._renderers[t]

    def info(self) -> dict:
        r = self.renderer(0)
        h, w = r.shapes[0]
        return {"name": self.name, "kind": self.kind,
                "slots": [{"label": s.label, "time": s.time} for s in self.slots],
                "width": w, "height": h, "levels": self.levels, "tile_px": TILE_PX,
                "resolution": max(64, self.levels[-1]["cols"]), "base": list(BASE_SIZE),
                "bands": r.bands, "modes": list(MODES), "units": r.index["units"],
                "wavelength_nm": [float(x) for x in r.estimator.wavelength_nm],
                "uncertainty_max": r.uncertainty_max, "has_quality": r.has_quality}


# ---------------------------------------------------------------------- parameter parsing
def _float(request: Request, name: str, default: float | None = None, lo: float = -math.inf,
           hi: float = math.inf) -> float:
    text = request.query_params.get(name)
    if text is None:
        if default is None:
            raise BadRequest(f"missing parameter {name}")
        return default
    try:
        value = float(text)
    except ValueError:
        raise BadRequest(f"parameter {name}={text[:40]!r} is not a number") from None
    if not (math.isfinite(value) and lo <= value <= hi):
        raise BadRequest(f"parameter {name}={value} is outside {lo}..{hi}")
    return value


def _int_text(text: str, name: str, hi: int) -> int:
    if not _INT.match(text):
        raise BadRequest(f"{name} {text[:40]!r} is not a non-negative integer")
    value = int(text)
    if value > hi:
        raise BadRequest(f"{name} {value} is outside 0..{hi}")
    return value


def _slot(request: Request, state: ViewerState) -> int:
    return _int_text(request.query_params.get("t", "0"), "slot t", len(state.slots) - 1)


def _display(request: Request, state: ViewerState) -> Display:
    mode = request.query_params.get("mode", "colour")
    if mode not in MODES:
        raise BadRequest(f"mode {mode[:40]!r} is not one of {', '.join(MODES)}")
    band = _int_text(request.query_params.get("band", "0"), "band", len(state.renderer(0).bands) - 1)
    ev = round(_float(request, "ev", 0.0, -40.0, 40.0), 2)
    return Display(mode, band if mode == "band" else 0, ev if mode in ("colour", "band") else 0.0)


def _png(data: bytes) -> Response:
    return Response(data, media_type="image/png", headers={"Cache-Control": "max-age=3600"})


async def _render(request: Request, key, render) -> Response:
    state: ViewerState = request.app.state.viewer
    cached = state.cache.get(key)
    if cached is not None:
        return _png(cached)
    if state.limiter is None:
        state.limiter = anyio.CapacityLimiter(state.max_parallel)
    data = await anyio.to_thread.run_sync(lambda: encode_png(render()), limiter=state.limiter)
    state.cache.put(key, data)
    return _png(data)


# ---------------------------------------------------------------------- endpoints
async def index_page(request: Request) -> Response:
    content, media = request.app.state.static["index.html"]
    return Response(content, media_type=media)


async def static_file(request: Request) -> Response:
    entry = request.app.state.static.get(request.path_params["name"])
    if entry is None or request.path_params["name"] == "index.html":
        raise HTTPException(404, "no such file")
    return Response(entry[0], media_type=entry[1], headers={"Cache-Control": "max-age=600"})


async def no_icon(request: Request) -> Response:
    return Response(status_code=204)


async def info(request: Request) -> Response:
    return JSONResponse(request.app.state.viewer.info())


async def tile(request: Request) -> Response:
    state: ViewerState = request.app.state.viewer
    p = request.path_params
    level_i = _int_text(p["level"], "tile level", len(state.levels) - 1)
    level = state.levels[level_i]
    col = _int_text(p["col"], "tile column", level["cols"] - 1)
    row = _int_text(p["row"], "tile row", level["rows"] - 1)
    t, display = _slot(request, state), _display(request, state)
    return await _render(request, ("tile", t, display, level_i, col, row),
                         lambda: state.renderer(t).render_tile(display, level, col, row))


async def base(request: Request) -> Response:
    state: ViewerState = request.app.state.viewer
    t, display = _slot(request, state), _display(request, state)
    return await _render(request, ("base", t, display),
                         lambda: state.renderer(t).render(display, 0, 1, 0, 1, *BASE_SIZE))


def _probe(state: ViewerState, t: int, lon: float, lat: float) -> dict:
    r = state.renderer(t)
    out = spectrum_in_store(r.index, r.store, r.estimator, lon, lat)
    x, y, z = out["XYZ"]
    s = x + y + z
    out["xy"] = [x / s, y / s] if s > 0 else [None, None]
    out["slot"] = t
    out["label"] = state.slots[t].label
    return out


async def spectrum(request: Request) -> Response:
    state: ViewerState = request.app.state.viewer
    lon = _float(request, "lon", lo=-540.0, hi=540.0)
    lat = _float(request, "lat", lo=-90.0, hi=90.0)
    if request.query_params.get("all") == "1":
        def all_slots():
            results = []
            for t in range(len(state.slots)):
                try:
                    results.append(_probe(state, t, lon, lat))
                except ConfigurationError as exc:
                    results.append({"slot": t, "label": state.slots[t].label, "error": str(exc)})
            return results
        return JSONResponse({"slots": await anyio.to_thread.run_sync(all_slots)})
    t = _slot(request, state)
    return JSONResponse(await anyio.to_thread.run_sync(lambda: _probe(state, t, lon, lat)))


async def auto_exposure(request: Request) -> Response:
    state: ViewerState = request.app.state.viewer
    lon = _float(request, "lon", lo=-540.0, hi=540.0)
    lat = _float(request, "lat", lo=-90.0, hi=90.0)
    fov = _float(request, "fov", 60.0, 1.0, 180.0)
    t, display = _slot(request, state), _display(request, state)
    ev = await anyio.to_thread.run_sync(lambda: state.renderer(t).auto_ev(display, lon, lat, fov))
    return JSONResponse({"ev": round(float(np.clip(ev, -40, 40)), 2)})


def probes_csv(probes: list[dict]) -> str:
    """CSV of probed spectra: ``#`` lines with each probe's direction, band values and CIE xy, then
    ``wavelength_nm`` and, per probe, the estimate and its 2σ."""
    buf = io.StringIO()
    for i, p in enumerate(probes, 1):
        bands = " ".join(f"{k}={v:.6g}" for k, v in p["bands"].items())
        xy = "n/a" if p["xy"][0] is None else f"{p['xy'][0]:.5f},{p['xy'][1]:.5f}"
        buf.write(f"# P{i}: slot {p['label']} lon_deg={p['lon_deg']:.6f} lat_deg={p['lat_deg']:.6f} "
                  f"CIE_xy={xy} {bands}\n")
    if probes:
        buf.write(f"# units: {probes[0]['units']}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["wavelength_nm", *(f"P{i}_{c}" for i in range(1, len(probes) + 1) for c in ("estimate", "2sigma"))])
    for j, wl in enumerate(probes[0]["wavelength_nm"] if probes else []):
        w.writerow([f"{wl:g}", *(f"{v:.7g}" for p in probes for v in (p["spectrum"][j], 2 * p["std"][j]))])
    return buf.getvalue()


async def probes(request: Request) -> Response:
    state: ViewerState = request.app.state.viewer
    t = _slot(request, state)
    texts = request.query_params.getlist("p")
    if not 1 <= len(texts) <= 16:
        raise BadRequest("give 1 to 16 probes as p=LON,LAT")
    points = []
    for text in texts:
        try:
            lon, lat = (float(v) for v in text.split(","))
        except ValueError:
            raise BadRequest(f"probe {text[:40]!r} is not LON,LAT") from None
        if not (math.isfinite(lon) and math.isfinite(lat) and abs(lat) <= 90):
            raise BadRequest(f"probe {text[:40]!r} is not a direction")
        points.append((lon, lat))
    rows = await anyio.to_thread.run_sync(lambda: [_probe(state, t, lon, lat) for lon, lat in points])
    return Response(probes_csv(rows), media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="{_safe(state.name)}_probes.csv"'})


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)[:64] or "product"


# ---------------------------------------------------------------------- errors
async def bad_request(request: Request, exc: Exception) -> Response:
    return JSONResponse({"error": str(exc)}, status_code=400)


async def unprocessable(request: Request, exc: Exception) -> Response:
    return JSONResponse({"error": str(exc)}, status_code=422)


async def damaged_product(request: Request, exc: Exception) -> Response:
    """A file of the product that is missing or fails its checksum (a panorama chunk): one line naming it, never
    a tile made of wrong numbers."""
    return JSONResponse({"error": str(exc)}, status_code=500)


async def http_error(request: Request, exc: HTTPException) -> Response:
    return JSONResponse({"error": exc.detail}, status_code=exc.status_code)


def host_name(header: str) -> str:
    """The name in an HTTP ``Host`` header, without its port: ``[::1]:8000`` → ``::1``, ``localhost:80`` →
    ``localhost``.  (Starlette's ``TrustedHostMiddleware`` cuts at the first colon, so it sees ``[`` for every
    IPv6 address and refused every request of a viewer bound to ``::1``.)"""
    header = header.strip().lower()
    if header.startswith("["):
        end = header.find("]")
        return header[1:end] if end > 0 else ""
    return header.rsplit(":", 1)[0] if header.count(":") == 1 else header


class LoopbackHostMiddleware:
    """Refuse (400) an HTTP request whose ``Host`` is not a loopback name: a page elsewhere that rebinds its DNS
    name to 127.0.0.1 cannot read the viewer."""

    allowed = frozenset({"127.0.0.1", "localhost", "::1"})

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] in ("http", "websocket"):
            headers = dict(scope.get("headers") or ())
            name = host_name(headers.get(b"host", b"").decode("latin-1"))
            if name not in self.allowed:
                await Response("Invalid host header", status_code=400, media_type="text/plain")(scope, receive, send)
                return
        await self.app(scope, receive, send)


def create_app(path: str | Path, host: str = "127.0.0.1", cache_bytes: int = 64 * 2**20,
               max_parallel: int = 2) -> Starlette:
    """The viewer application for a product or a processed series (module docstring).

    Bound to a loopback address, it answers only requests whose ``Host`` is a loopback name (a web page
    elsewhere cannot reach it through DNS rebinding)."""
    state = ViewerState(path, cache_bytes=cache_bytes, max_parallel=max_parallel)
    routes = [Route("/", index_page), Route("/favicon.ico", no_icon), Route("/static/{name:path}", static_file),
              Route("/api/info", info),
              Route("/api/tile/{level}/{col}/{row}.png", tile), Route("/api/base.png", base),
              Route("/api/spectrum", spectrum), Route("/api/auto-exposure", auto_exposure),
              Route("/api/probes.csv", probes)]
    middleware = []
    if host in LOCAL_HOSTS:
        middleware.append(Middleware(LoopbackHostMiddleware))
    app = Starlette(routes=routes, middleware=middleware,
                    exception_handlers={BadRequest: bad_request, ConfigurationError: unprocessable,
                                        InputFileError: damaged_product, HTTPException: http_error})
    app.state.viewer = state
    app.state.static = load_static()
    return app


def serve(path: str | Path, host: str = "127.0.0.1", port: int = 8000, open_browser: bool = False,
          on_ready=None) -> None:
    """Serve the viewer with uvicorn until interrupted (``on_ready(url)`` is called once it listens)."""
    import uvicorn  # lazy: only the server needs it, the application (and its tests) do not

    check_listen_address(host, port)
    app = create_app(path, host=host)
    config = uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False)
    server = uvicorn.Server(config)

    def announce():
        while not server.started and not server.should_exit:
            threading.Event().wait(0.05)
        if server.started:
            url = f"http://{host_port('127.0.0.1' if host in ('0.0.0.0', '::') else host, bound_port(server, port))}/"
            if on_ready is not None:
                on_ready(url)
            if open_browser:
                webbrowser.open(url)

    threading.Thread(target=announce, daemon=True).start()
    server.run()



def bound_port(server, asked: int) -> int:
    """The port a started uvicorn ``server`` listens on: ``asked``, or the one the system picked for 0."""
    if asked:
        return asked
    for srv in getattr(server, "servers", []):
        for sock in srv.sockets:
            return int(sock.getsockname()[1])
    return asked


#: TCP port numbers (0: any free port the system picks).
PORT_RANGE = (0, 65535)


def check_port_number(port: int) -> None:
    """A port outside :data:`PORT_RANGE` is a ``ConfigurationError`` (a usage error, before anything is opened)."""
    if not PORT_RANGE[0] <= port <= PORT_RANGE[1]:
        raise ConfigurationError(f"--port {port}: a TCP port is {PORT_RANGE[0]}..{PORT_RANGE[1]}")


def host_port(host: str, port: int) -> str:
    """``host:port`` as a URL writes it (an IPv6 address in brackets)."""
    return f"[{host}]:{port}" if ":" in host and not host.startswith("[") else f"{host}:{port}"


def check_listen_address(host: str, port: int) -> None:
    """A one-line error now rather than uvicorn's log line and exit when the port cannot be bound: a port out of
    range or a host that does not resolve is a ``ConfigurationError`` (exit 2), a port in use or an address
    not of this machine a :class:`CannotListenError` (exit 1)."""
    check_port_number(port)
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise ConfigurationError(f"host {host!r} cannot be resolved ({exc.strerror})") from None
    family, _, _, _, address = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
        except OSError as exc:
            raise CannotListenError(f"cannot listen on {host_port(host, port)}: {exc.strerror or exc}; choose "
                                    "another --port") from None
