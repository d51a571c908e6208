"""The viewer's server: tiles equal to the store's pixels through the tone curve, spectra and CSV equal to
``spectrum_at``, nothing outside the product reachable, malformed requests 4xx, bursts bounded in memory."""

from __future__ import annotations

import csv
import hashlib
import http.client
import io
import json
import re
import socket
import threading
import time
import tracemalloc
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import cv2
import numpy as np
import pytest

pytest.importorskip("starlette", reason="starlette is not installed (pip install 'omnispectral[view]')")

from omnispectral.cli import main
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.estimator import estimator_params
from omnispectral.product.exports import reinhard_srgb8
from omnispectral.product.spectra import spectrum_at
from omnispectral.rig import load_preset
from omnispectral.view.server import STATIC_DIR, create_app, load_static, probes_csv, view_slots
from omnispectral.view.tiles import Display, SlotRenderer, TileCache, viewer_levels

BANDS = ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"]
H, W = 512, 1024  # level 0; levels 1-3 halve it (128-px chunks)


def synthetic_bands(h: int, w: int) -> np.ndarray:
    """Smooth positive six-band radiance (DN/s) varying with longitude and latitude, one uncovered patch."""
    lon = (np.arange(w) + 0.5) / w * 2 * np.pi
    lat = (np.arange(h) + 0.5) / h * np.pi
    base = 1000 * (1.5 + np.sin(lon)[None, :] * np.sin(lat)[:, None])  # brightest at lon -90°, lat 0
    bands = np.stack([base * (0.6 + 0.1 * k) * (1 + 0.3 * np.cos(lon * (k + 1)))[None, :] for k in range(6)], -1)
    bands = bands.astype(np.float32)
    bands[h - 20:, :40] = np.nan  # not covered by any direction
    return bands


@pytest.fixture(scope="module")
def tiny_product(tmp_path_factory):
    """A product directory written through the public store API: synthetic bands, the small rig's estimator."""
    root = tmp_path_factory.mktemp("viewprod")
    bands = synthetic_bands(H, W)
    store = PanoramaStore.create(root / "panorama.zarr", H, W, 6, tile=128, attrs={"bands": BANDS}, fingerprint={})
    arr0 = store.array(0, mode="r+")
    arr0[:] = bands
    for k in range(1, len(store.shapes)):
        arr = store.array(k, mode="r+")
        for ty in range(store.n_chunks(k)[0]):
            for tx in range(store.n_chunks(k)[1]):
                r0, r1, c0, c1 = store.chunk_rect(k, ty, tx)
                arr[r0:r1, c0:c1] = store.downsample_chunk(k, ty, tx)
    index = {"format": "omnispectral-product", "width": W, "height": H, "bands": BANDS,
             "units": "DN per second of exposure", "estimator": {"params": estimator_params(load_preset("small"))}}
    (root / "product.json").write_text(json.dumps(index))
    return root


@pytest.fixture(scope="module")
def client(tiny_product):
    from starlette.testclient import TestClient

    with TestClient(create_app(tiny_product), base_url="http://127.0.0.1") as c:
        yield c


@contextmanager
def running_server(app):
    """The application on a real uvicorn server on a free loopback port (requests reach it unnormalised)."""
    import uvicorn

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="error"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    for _ in range(200):
        if server.started:
            break
        time.sleep(0.02)
    try:
        yield port
    finally:
        server.should_exit = True
        thread.join(10)


def raw_get(port: int, path: str, host: str = "127.0.0.1") -> tuple[int, bytes]:
    """GET with the path sent byte for byte (no client-side ``..`` removal or quoting)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    conn.putrequest("GET", path, skip_host=True, skip_accept_encoding=True)
    conn.putheader("Host", host)
    conn.endheaders()
    resp = conn.getresponse()
    body = resp.read()
    conn.close()
    return resp.status, body


# ------------------------------------------------------------------ tiles
def test_viewer_levels_are_power_of_two_grids_up_to_the_panorama_width():
    assert viewer_levels(952) == [{"width": 512, "cols": 2, "rows": 1}, {"width": 1024, "cols": 4, "rows": 2}]
    levels = viewer_levels(46_000)
    assert [lv["cols"] for lv in levels] == [2, 4, 8, 16, 32, 64, 128, 256]
    assert levels[-1]["width"] >= 46_000 > levels[-2]["width"]


@pytest.mark.parametrize(("level", "mode", "band", "ev"), [(1, "band", 3, 1.5), (0, "band", 0, -2.0),
                                                           (1, "colour", 0, 0.5)])
def test_tiles_are_the_store_pixels_through_exposure_and_tone_curve(tiny_product, level, mode, band, ev):
    r = SlotRenderer(tiny_product)
    lv = viewer_levels(W, 256)[level]  # widths 512 and 1024: the stored levels 1 and 0 exactly
    store = PanoramaStore.open(tiny_product / "panorama.zarr")
    src = store.read(0 if lv["width"] == W else 1)
    display = Display(mode, band, ev)
    for col, row in ((0, 0), (lv["cols"] - 1, lv["rows"] - 1)):
        tile = r.render_tile(display, lv, col, row)
        win = src[row * 256:(row + 1) * 256, col * 256:(col + 1) * 256]
        if mode == "band":
            expected = reinhard_srgb8(win[..., band:band + 1] * 2**ev / r.reference[f"band{band}"])
            expected = np.repeat(expected, 3, axis=-1)
        else:
            rgb = win @ r.colour_matrix + r.colour_offset
            expected = reinhard_srgb8(rgb * 2**ev / r.reference["colour"])
        # away from uncovered pixels (bilinear weights of 0 still let a NaN neighbour through)
        finite = cv2.erode(np.isfinite(win).all(axis=-1).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        assert tile.shape == (256, 256, 3)
        assert np.abs(tile[finite].astype(int) - expected[finite]).max() <= 1
    # the uncovered patch (bottom-left) is black, the rest is not
    tile = r.render_tile(Display("band", 0, 0.0), viewer_levels(W, 256)[1], 0, 1)
    assert tile[-10:, :30].max() == 0 and tile[:200].mean() > 20


def test_exposure_and_auto_exposure(tiny_product):
    r = SlotRenderer(tiny_product)
    lv = viewer_levels(W, 256)[0]
    dark, bright = (r.render_tile(Display("colour", 0, ev), lv, 1, 0).mean() for ev in (-2.0, 2.0))
    assert bright > dark + 40
    # the bright side (lon -90°) needs less exposure than the dark side (lon +90°)
    assert r.auto_ev(Display(), -90, 0, 40) < r.auto_ev(Display(), 90, 0, 40) - 1


def test_uncertainty_tiles_show_the_relative_posterior_std(tiny_product):
    r = SlotRenderer(tiny_product)
    lv = viewer_levels(W, 256)[0]
    tile = r.render_tile(Display("uncertainty"), lv, 0, 0)
    bands = PanoramaStore.open(tiny_product / "panorama.zarr").read(1)[100:101, 100:101]
    std = r.estimator.posterior_std(bands.reshape(-1, 6))
    est = r.estimator.estimate(bands.reshape(-1, 6))
    rel = float(np.sqrt(np.mean(std**2)) / np.sqrt(np.mean(est**2)))
    idx = int(np.clip(rel / r.uncertainty_max, 0, 1) * 255)
    lut = r._lut
    # the tile's colour at that pixel is the colour map's entry for its relative std (within 8 entries)
    match = np.abs(lut.astype(int) - tile[100, 100].astype(int)).sum(axis=1).argmin()
    assert abs(int(match) - idx) <= 8 and 0 < rel < 2


def test_registration_tiles_show_confidence_and_occlusion(tiny_product, tmp_path):
    import shutil

    import zarr

    from omnispectral.errors import ConfigurationError

    with pytest.raises(ConfigurationError, match="no registration-quality layer"):
        SlotRenderer(tiny_product).render_tile(Display("registration"), viewer_levels(W, 256)[0], 0, 0)
    prod = tmp_path / "with_quality"
    shutil.copytree(tiny_product, prod)
    group = zarr.open_group(str(prod / "panorama.zarr"), mode="r+", zarr_format=3)
    q = np.zeros((H, W, 2), np.float32)
    q[..., 0] = np.linspace(0, 1, W)[None, :]  # confidence rising from left to right
    q[40:60, 300:340, 1] = 1.0  # an occluded patch
    group.create_array("quality", data=q, chunks=(128, 128, 2))
    r = SlotRenderer(prod)
    assert r.has_quality
    tile = r.render(Display("registration"), 0.0, 1.0, 0.0, 1.0, W, H)
    lut = r._lut
    for col in (10, 500, 1000):
        idx = int(np.clip(q[100, col, 0], 0, 1) * 255)
        match = np.abs(lut.astype(int) - tile[100, col].astype(int)).sum(axis=1).argmin()
        assert abs(int(match) - idx) <= 2
    assert tuple(tile[50, 320]) == (230, 30, 30) and tuple(tile[100, 320]) != (230, 30, 30)


def test_tile_cache_is_bounded_in_bytes():
    cache = TileCache(max_bytes=1000)
    for i in range(10):
        cache.put(i, bytes(300))
    assert cache.n_bytes <= 1000 and len(cache) == 3 and cache.get(9) is not None and cache.get(0) is None


# ------------------------------------------------------------------ endpoints
def test_spectrum_and_csv_equal_spectrum_at(client, tiny_product):
    got = client.get("/api/spectrum", params={"lon": 33.3, "lat": -12.5}).json()
    ref = spectrum_at(tiny_product, 33.3, -12.5)
    np.testing.assert_array_equal(got["spectrum"], ref["spectrum"])
    np.testing.assert_array_equal(got["std"], ref["std"])
    assert got["bands"] == ref["bands"]
    x, y, z = ref["XYZ"]
    np.testing.assert_allclose(got["xy"], [x / (x + y + z), y / (x + y + z)], rtol=1e-12)
    text = client.get("/api/probes.csv", params=[("p", "33.3,-12.5"), ("p", "-100,40")]).text
    rows = list(csv.reader(io.StringIO("\n".join(li for li in text.splitlines() if not li.startswith("#")))))
    assert rows[0] == ["wavelength_nm", "P1_estimate", "P1_2sigma", "P2_estimate", "P2_2sigma"]
    table = np.array(rows[1:], float)
    ref2 = spectrum_at(tiny_product, -100, 40)
    np.testing.assert_allclose(table[:, 0], ref["wavelength_nm"])
    np.testing.assert_allclose(table[:, 1], ref["spectrum"], rtol=1e-6)
    np.testing.assert_allclose(table[:, 2], 2 * np.array(ref["std"]), rtol=1e-6)
    np.testing.assert_allclose(table[:, 3], ref2["spectrum"], rtol=1e-6)
    assert "lon_deg=33.300000 lat_deg=-12.500000" in text and "B:G=" in text


def test_uncovered_direction_is_a_422_with_the_reason(client):
    r = client.get("/api/spectrum", params={"lon": -178, "lat": -85})
    assert r.status_code == 422 and "not covered" in r.json()["error"]


def test_info_describes_levels_and_bands(client):
    info = client.get("/api/info").json()
    assert info["kind"] == "product" and info["bands"] == BANDS and info["width"] == W
    assert info["levels"][-1]["width"] >= W and len(info["wavelength_nm"]) == 61


@pytest.mark.parametrize("url", [
    "/api/tile/2/0/0.png", "/api/tile/0/2/0.png", "/api/tile/0/0/1.png", "/api/tile/-1/0/0.png",
    "/api/tile/a/0/0.png", "/api/tile/1e3/0/0.png", "/api/tile/99999999999999/0/0.png", "/api/tile/0/0/0",
    "/api/tile/0/0/0.png?ev=inf", "/api/tile/0/0/0.png?ev=abc", "/api/tile/0/0/0.png?ev=1e400",
    "/api/tile/0/0/0.png?mode=../../etc", "/api/tile/0/0/0.png?band=6", "/api/tile/0/0/0.png?band=-1",
    "/api/tile/0/0/0.png?t=1", "/api/tile/0/0/0.png?t=x", "/api/base.png?mode=", "/api/spectrum?lon=1",
    "/api/spectrum?lon=1&lat=91", "/api/spectrum?lon=nan&lat=0", "/api/auto-exposure?lon=0&lat=0&fov=0",
    "/api/probes.csv", "/api/probes.csv?p=abc", "/api/probes.csv?p=1,2,3", "/api/probes.csv?p=0,95",
    "/api/probes.csv?" + "&".join(["p=0,0"] * 17), "/api/nothing", "/static/", "/static/index.html",
])
def test_malformed_requests_are_4xx_with_a_message(client, url):
    r = client.get(url)
    assert 400 <= r.status_code < 500, (url, r.status_code)
    assert "Traceback" not in r.text and r.json()["error"]


TRAVERSALS = ["/static/../../../../etc/passwd", "/static/..%2f..%2f..%2f..%2fetc%2fpasswd",
              "/static/%2e%2e/%2e%2e/%2e%2e/product.json", "/../../../../etc/passwd", "/static//etc/passwd",
              "/static/vendor/../../../../../product.json", "/static/%2fetc%2fpasswd", "/static/..\\..\\product.json",
              "/api/tile/../../product.json", "/static/vendor/three/../../../server.py", "/static/%00",
              "/static/..%252f..%252fproduct.json", "/product.json", "/panorama.zarr/zarr.json"]


def test_no_request_path_reaches_the_file_system(tiny_product):
    app = create_app(tiny_product)
    with running_server(app) as port:
        status, body = raw_get(port, "/static/viewer.js")
        assert status == 200 and body == (STATIC_DIR / "viewer.js").read_bytes()
        for path in TRAVERSALS:
            status, body = raw_get(port, path)
            assert 400 <= status < 500, (path, status)
            assert b"root:" not in body and b"omnispectral-product" not in body and b"import " not in body
        # a page elsewhere that resolves its own name to 127.0.0.1 (DNS rebinding) is refused
        assert raw_get(port, "/api/info", host="attacker.example")[0] == 400


def test_fifty_parallel_tile_requests_are_served_with_bounded_memory(tiny_product):
    app = create_app(tiny_product, cache_bytes=2 * 2**20, max_parallel=2)
    levels = app.state.viewer.levels
    urls = [f"/api/tile/{k}/{c}/{r}.png?ev={ev}" for ev in (-1, 0, 1, 2, 3) for k, lv in enumerate(levels)
            for c in range(lv["cols"]) for r in range(lv["rows"])][:50]
    assert len(set(urls)) == 50
    with running_server(app) as port:
        raw_get(port, urls[0])  # warm up (imports, first zarr open)
        tracemalloc.start()
        try:
            with ThreadPoolExecutor(50) as pool:
                results = list(pool.map(lambda u: raw_get(port, u), urls))
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    assert all(status == 200 for status, _ in results)
    images = [cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR) for _, body in results]
    assert all(im is not None and im.shape == (256, 256, 3) for im in images)
    # two renders at a time: each holds a ≤ 258² × 6 float32 window and a few 256² × 3 planes (~5 MB);
    # without the limiter the same burst peaks at ~300 MiB (measured with max_parallel=50)
    assert peak < 48 * 2**20, f"peak traced memory {peak / 2**20:.1f} MiB"
    assert app.state.viewer.cache.n_bytes <= 2 * 2**20


# ------------------------------------------------------------------ command line
def test_view_slots_and_cli_errors(tiny_product, tmp_path, capsys):
    assert view_slots(tiny_product)[0] == "product"
    with pytest.raises(InputFileError, match="neither a product"):
        view_slots(tmp_path)
    assert main(["view", str(tmp_path / "missing")]) == 1
    assert "does not exist" in capsys.readouterr().err
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        # a busy port: the work failed (1), one line naming host:port, nothing opened first
        assert main(["view", str(tiny_product), "--port", str(port)]) == 1
        err = capsys.readouterr().err
        assert f"cannot listen on 127.0.0.1:{port}" in err and err.count("\n") == 1
        # another address than loopback: a warning first (here the port is taken on all addresses too)
        assert main(["view", str(tiny_product), "--port", str(port), "--host", "0.0.0.0"]) == 1
    err = capsys.readouterr().err
    assert "warning" in err and "0.0.0.0" in err and f"cannot listen on 0.0.0.0:{port}" in err


@pytest.mark.parametrize("port", ["99999", "65536", "-1"])
def test_view_port_out_of_range_is_a_one_line_usage_error(tiny_product, capsys, port):
    assert main(["view", str(tiny_product), "--port", port]) == 2
    err = capsys.readouterr().err
    assert f"--port {port}: a TCP port is 0..65535" in err and err.count("\n") == 1 and "Traceback" not in err


def test_probes_csv_of_nothing_is_refused(client):
    with pytest.raises(ConfigurationError):
        Display("relit")
    assert probes_csv([]).startswith("wavelength_nm")


def test_every_file_the_page_loads_is_in_the_package_with_its_licence():
    table = load_static()
    html = table["index.html"][0].decode()
    refs = re.findall(r'"\.?/?static/([^"]+)"', html)
    assert len(refs) >= 6 and all(r in table for r in refs), [r for r in refs if r not in table]
    versions = json.loads(table["vendor/VERSIONS.json"][0])
    assert set(versions) == {"three", "@photo-sphere-viewer/core", "@photo-sphere-viewer/equirectangular-tiles-adapter"}
    for entry in versions.values():
        assert any(f.endswith("LICENSE") for f in entry["files"]) and entry["license"] == "MIT"
        for name, digest in entry["files"].items():
            assert hashlib.sha256(table[f"vendor/{name}"][0]).hexdigest() == digest
