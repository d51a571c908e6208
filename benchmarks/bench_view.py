"""Viewer tile latency over HTTP (run by hand; numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_view.py [--product DIR] [--large] [--json-out FILE]

Serves a product with ``omnispectral.view`` on a real uvicorn server (loopback) and requests tiles one
after the other as a client would:

* ``cold``: every tile of every viewer level at three exposures, shuffled, each requested once (nothing
  cached: read the Zarr window, tone map, PNG-encode);
* ``warm``: the same requests again (served from the tile cache);
* ``burst``: 50 distinct uncached tiles requested at once (wall time for all, as a browser opening a view).

Products: the demo product (``omnispectral simulate --preset small`` + ``process``, 952 × 476; made in a
temporary directory unless ``--product`` is given) and, with ``--large``, a synthetic 14336 × 7168
(103 Mpx) six-band store written through ``PanoramaStore`` (512-px chunks, Blosc-zstd, full pyramid)
with the small rig's estimator, to show that latency does not grow with the panorama.
"""

from __future__ import annotations

import argparse
import http.client
import json
import socket
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from omnispectral.cli import main as cli_main
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.estimator import estimator_params
from omnispectral.rig import load_preset
from omnispectral.view.server import create_app

BANDS = ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"]


def demo_product(root: Path) -> Path:
    cli_main(["simulate", "--preset", "small", "-o", str(root / "session")])
    cli_main(["process", str(root / "session"), "-o", str(root / "product"), "--json"])
    return root / "product"


def large_product(root: Path, height: int = 7168, tile: int = 512) -> Path:
    """A synthetic ``2h × h`` store: smooth six-band radiance with texture, quantised so it compresses."""
    width = 2 * height
    store = PanoramaStore.create(root / "panorama.zarr", height, width, 6, tile, attrs={"bands": BANDS},
                                 fingerprint={"synthetic": height})
    rng = np.random.default_rng(0)
    texture = rng.uniform(0.8, 1.2, (tile, tile)).astype(np.float32)
    arr = store.array(0, mode="r+")
    ny, nx = store.n_chunks(0)
    for ty in range(ny):
        for tx in range(nx):
            r0, r1, c0, c1 = store.chunk_rect(0, ty, tx)
            lon = (np.arange(c0, c1) + 0.5) / width * 2 * np.pi
            lat = (np.arange(r0, r1) + 0.5) / height * np.pi
            base = 1000 * (1.5 + np.sin(lon)[None, :] * np.sin(lat)[:, None]) * texture[: r1 - r0, : c1 - c0]
            chunk = np.stack([base * (0.6 + 0.1 * k) for k in range(6)], -1)
            arr[r0:r1, c0:c1] = np.round(chunk).astype(np.float32)
        print(f"\rlevel 0: row {ty + 1}/{ny}", end="", flush=True)
    for k in range(1, len(store.shapes)):
        arr = store.array(k, mode="r+")
        for ty in range(store.n_chunks(k)[0]):
            for tx in range(store.n_chunks(k)[1]):
                r0, r1, c0, c1 = store.chunk_rect(k, ty, tx)
                arr[r0:r1, c0:c1] = store.downsample_chunk(k, ty, tx)
        print(f"\rlevel {k} done          ", end="", flush=True)
    print()
    index = {"format": "omnispectral-product", "width": width, "height": height, "bands": BANDS,
             "units": "DN per second of exposure", "estimator": {"params": estimator_params(load_preset("small"))}}
    (root / "product.json").write_text(json.dumps(index))
    return root


class Server:
    def __init__(self, app):
        import uvicorn

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="error"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self):
        self.thread.start()
        while not self.server.started:
            time.sleep(0.02)
        return self

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(10)

    def get(self, path: str) -> float:
        t0 = time.perf_counter()
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=120)
        conn.request("GET", path)
        resp = conn.getresponse()
        body = resp.read()
        conn.close()
        if resp.status != 200 or not body:
            raise RuntimeError(f"{path}: HTTP {resp.status}")
        return time.perf_counter() - t0


def percentiles_ms(times_s: list[float]) -> dict:
    a = np.asarray(times_s) * 1000
    return {"n": int(a.size), "p50_ms": float(np.percentile(a, 50)), "p95_ms": float(np.percentile(a, 95)),
            "max_ms": float(a.max())}


def bench(product: Path, run: int = 0, max_cold: int = 300) -> dict:
    """One run; ``run`` shifts the exposures so that no two runs share a cached tile."""
    t0 = time.perf_counter()
    app = create_app(product)
    open_s = time.perf_counter() - t0
    levels = app.state.viewer.levels
    urls = [f"/api/tile/{k}/{c}/{r}.png?ev={ev + 0.1 * run}" for ev in (-1, 0, 1) for k, lv in enumerate(levels)
            for c in range(lv["cols"]) for r in range(lv["rows"])]
    rng = np.random.default_rng(run)
    urls = [urls[i] for i in rng.permutation(len(urls))[:max_cold]]
    with Server(app) as srv:
        srv.get("/api/base.png")  # first request: imports, zarr metadata
        cold = [srv.get(u) for u in urls]
        warm = [srv.get(u) for u in urls]
        top, last = len(levels) - 1, levels[-1]
        burst_urls = [f"/api/tile/{top}/{i % last['cols']}/{(i // last['cols']) % last['rows']}.png"
                      f"?ev={3 + 0.25 * i + 0.1 * run}" for i in range(50)]
        t0 = time.perf_counter()
        with ThreadPoolExecutor(50) as pool:
            list(pool.map(srv.get, burst_urls))
        burst_s = time.perf_counter() - t0
    h, w = app.state.viewer.renderer(0).shapes[0]
    return {"product": str(product), "width": w, "height": h, "megapixels": w * h / 1e6, "open_s": open_s,
            "levels": [lv["width"] for lv in levels], "cold": percentiles_ms(cold), "warm": percentiles_ms(warm),
            "burst50_s": burst_s, "n_burst_distinct": len(set(burst_urls))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--product", type=Path, default=None, help="product directory (default: make the demo one)")
    ap.add_argument("--large", action="store_true", help="also a synthetic 103-Mpx product")
    ap.add_argument("--repeat", type=int, default=3, help="runs per product (medians are reported)")
    ap.add_argument("--json-out", type=Path, default=None)
    args = ap.parse_args()
    results = []
    with tempfile.TemporaryDirectory(prefix="bench-view-") as tmp:
        product = args.product or demo_product(Path(tmp) / "demo")
        results += [bench(product, run) for run in range(args.repeat)]
        if args.large:
            t0 = time.perf_counter()
            big = large_product(Path(tmp) / "large")
            print(f"large store written in {time.perf_counter() - t0:.0f} s")
            results += [bench(big, run) for run in range(args.repeat)]
    for r in results:
        print(f"{r['width']}x{r['height']} ({r['megapixels']:.1f} Mpx): cold p50 {r['cold']['p50_ms']:.1f} ms, "
              f"p95 {r['cold']['p95_ms']:.1f} ms (n={r['cold']['n']}); cached p50 {r['warm']['p50_ms']:.2f} ms, "
              f"p95 {r['warm']['p95_ms']:.2f} ms; 50 parallel uncached tiles {r['burst50_s']:.2f} s; "
              f"open {r['open_s']:.1f} s")
    for width in sorted({r["width"] for r in results}):
        runs = [r for r in results if r["width"] == width]
        med = {f"{part}_{q}": float(np.median([r[part][q] for r in runs]))
               for part in ("cold", "warm") for q in ("p50_ms", "p95_ms")}
        print(f"median of {len(runs)} runs, width {width}: " + ", ".join(f"{k} {v:.2f}" for k, v in med.items())
              + f", burst50 {np.median([r['burst50_s'] for r in runs]):.2f} s")
    if args.json_out:
        args.json_out.write_text(json.dumps({"runs": results}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
