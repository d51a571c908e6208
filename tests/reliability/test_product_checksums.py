"""Damage in a product is never used as good data (docs/reliability.md): panorama chunks and merged files carry
checksums, ``product verify`` names what is missing or damaged, the readers a user meets refuse it in one line,
and a rerun of ``process`` repairs it into the very panorama it had."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from omnispectral.cli import main
from omnispectral.errors import InputFileError
from omnispectral.mosaic.sources import MergedDirections
from omnispectral.mosaic.store import QUALITY, PanoramaStore
from omnispectral.product.process import process

from .test_fault_injection import simulate_tiny

#: A small tile: the tiny panorama gets several chunks and a pyramid above them.
TILE_PX = 64
#: The level-0 chunk the tests damage (row, column): inside the covered panorama.
CHUNK = (1, 2)


def verify_product(product: Path) -> dict:
    from omnispectral.product.verify import verify_product as verify  # imported here: each test fails on its own

    return verify(product)


def run_process(session: Path, product: Path) -> dict:
    return process(session, product, tile=TILE_PX, progress=False, report=False)


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> tuple[Path, Path]:
    """A tiny session and its product (12 directions, 6 exposures, 96 × 52 px; tile 64 px)."""
    root = tmp_path_factory.mktemp("checksums")
    simulate_tiny(root / "s")
    run_process(root / "s", root / "p")
    return root / "s", root / "p"


@pytest.fixture
def product(made, tmp_path) -> Path:
    """A copy of the product that a test may damage."""
    shutil.copytree(made[1], tmp_path / "p")
    return tmp_path / "p"


def all_arrays(product: Path) -> dict[str, np.ndarray]:
    """Every level of the panorama and its quality layer."""
    store = PanoramaStore.open(product / "panorama.zarr")
    out = {str(k): store.read(k) for k in range(len(store.shapes))}
    if store.has_quality():
        out[QUALITY] = store.read_quality()
    return out


def assert_same_panorama(got: Path, want: Path) -> None:
    a, b = all_arrays(got), all_arrays(want)
    assert a.keys() == b.keys()
    for name in a:  # bit for bit (NaN where uncovered on both)
        np.testing.assert_array_equal(a[name].view(np.uint32), b[name].view(np.uint32), err_msg=name)


def flip_bytes(path: Path) -> None:
    """Invert 8 bytes in the middle of a file (same size: only a checksum can tell)."""
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 8] = bytes(b ^ 0xFF for b in data[mid:mid + 8])
    path.write_bytes(bytes(data))


def chunk_path(product: Path, array: str = "0", ty: int = CHUNK[0], tx: int = CHUNK[1]) -> Path:
    return product / "panorama.zarr" / array / "c" / "0" / str(ty) / str(tx)


def chunk_lonlat(product: Path, ty: int = CHUNK[0], tx: int = CHUNK[1]) -> tuple[float, float]:
    """A direction inside a level-0 chunk."""
    store = PanoramaStore.open(product / "panorama.zarr")
    h, w = store.shapes[0]
    row, col = ty * TILE_PX + TILE_PX // 2, tx * TILE_PX + TILE_PX // 2
    return (col + 0.5) / w * 360.0 - 180.0, 90.0 - (row + 0.5) / h * 180.0


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def verify_cli(product: Path, capsys) -> tuple[int, str]:
    code = main(["product", "verify", str(product)])
    return code, capsys.readouterr().out


# ------------------------------------------------------------------ an undamaged product
def test_an_undamaged_product_verifies(product, capsys):
    code, out = verify_cli(product, capsys)
    assert code == 0, out
    assert "all good" in out
    report = verify_product(product)
    assert report["ok"] and report["problems"] == []
    assert report["n_chunks"] > 10 and report["n_merged_files"] == 36  # 12 directions: A, B and B's parallax
    assert main(["product", "verify", str(product), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ok"] is True


def test_chunk_markers_and_merged_json_record_checksums(product):
    store = PanoramaStore.open(product / "panorama.zarr")
    marker = store.chunk_records(0)[CHUNK]
    assert {"crc32", "bytes"} <= set(marker["chunk"]) and {"crc32", "bytes"} <= set(marker["quality_chunk"])
    assert marker["chunk"]["bytes"] == chunk_path(product).stat().st_size
    assert "chunk" not in store.done_markers(0)[CHUNK]  # the statistics alone, as before
    codecs = json.loads((product / "panorama.zarr" / "0" / "zarr.json").read_text())["codecs"]
    assert codecs[-1]["name"] == "crc32c"  # every Zarr reader checks the chunks
    meta = json.loads((product / "merged" / "merged.json").read_text())
    image = meta["directions"][0]["images"]["B"]
    assert {"crc32", "bytes"} <= set(image["checksum"]) and {"crc32", "bytes"} <= set(image["parallax"]["checksum"])


# ------------------------------------------------------------------ a damaged or deleted chunk
DAMAGES = {
    "flipped level 0": ("0", flip_bytes),
    "deleted level 0, marker kept": ("0", Path.unlink),
    "flipped quality layer": (QUALITY, flip_bytes),
}


@pytest.mark.parametrize("case", list(DAMAGES))
def test_a_damaged_chunk_is_named_refused_and_repaired(made, product, tmp_path, capsys, case):
    session, original = made
    array, damage = DAMAGES[case]
    bad = chunk_path(product, array)
    damage(bad)

    code, out = verify_cli(product, capsys)
    assert code == 1 and str(bad) in out, out
    assert [p["file"] for p in verify_product(product)["problems"]] == [str(bad)]

    # the readers a user meets refuse it in one line naming the chunk file
    lon, lat = chunk_lonlat(product)
    assert main(["spectrum", str(product), "--lon", f"{lon:.4f}", "--lat", f"{lat:.4f}", "--json"]) == 1
    assert str(bad) in one_error_line(capsys)
    assert main(["export", str(product), "--format", "png", "-o", str(tmp_path / "x.png")]) == 1
    line = one_error_line(capsys)
    assert str(bad) in line and ("damaged" in line or "missing" in line), line
    assert not (tmp_path / "x.png").exists()

    # a rerun recomputes it: the very panorama the product had
    index = run_process(session, product)
    assert [c["file"] for c in index["repaired"]["chunks"]] == [str(bad.relative_to(product / "panorama.zarr"))]
    assert json.loads((product / "product.json").read_text())["repaired"]["chunks"]
    assert_same_panorama(product, original)
    assert verify_cli(product, capsys)[0] == 0


def test_a_damaged_pyramid_chunk_is_repaired(made, product, capsys):
    session, original = made
    bad = chunk_path(product, "1", 0, 0)
    flip_bytes(bad)
    assert verify_cli(product, capsys)[0] == 1
    with pytest.raises(InputFileError, match="damaged"):
        PanoramaStore.open(product / "panorama.zarr").read(1)
    import zarr

    with pytest.raises(ValueError, match="checksum"):  # any Zarr reader: the arrays' crc32c codec
        zarr.open_array(str(product / "panorama.zarr" / "1"), mode="r", zarr_format=3)[:]
    run_process(session, product)
    assert_same_panorama(product, original)


def test_the_viewer_refuses_a_damaged_chunk_in_one_line(product):
    pytest.importorskip("starlette")
    from starlette.testclient import TestClient

    from omnispectral.view.server import create_app

    bad = chunk_path(product, "0")
    flip_bytes(bad)
    with TestClient(create_app(product), base_url="http://127.0.0.1") as client:
        lon, lat = chunk_lonlat(product)
        r = client.get("/api/spectrum", params={"lon": lon, "lat": lat})
        assert r.status_code == 500
        assert str(bad) in r.json()["error"] and "\n" not in r.json()["error"]
    from omnispectral.view.tiles import SlotRenderer

    with pytest.raises(InputFileError, match="damaged") as err:  # what the tiles are drawn from
        SlotRenderer(product).read(0, slice(0, 2 * TILE_PX), slice(0, 3 * TILE_PX))
    assert str(bad) in str(err.value)


# ------------------------------------------------------------------ a damaged merged file
def test_a_damaged_merged_file_is_named_refused_and_merged_again(made, product, capsys):
    session, original = made
    bad = product / "merged" / "d0004_B.npy"
    flip_bytes(bad)

    code, out = verify_cli(product, capsys)
    assert code == 1 and str(bad) in out, out
    source = next(s for s in MergedDirections.open(product / "merged").sources()
                  if s.direction == 4 and s.camera == "B")
    with pytest.raises(InputFileError, match="damaged: checksum") as err:
        source.read()
    assert str(bad) in str(err.value) and "\n" not in str(err.value)

    index = run_process(session, product)
    assert [m["file"] for m in index["repaired"]["merged"]] == [str(bad)]
    assert bad.read_bytes() == (original / "merged" / "d0004_B.npy").read_bytes()  # merged again from the frames
    assert_same_panorama(product, original)
    assert verify_cli(product, capsys)[0] == 0


def test_a_deleted_parallax_map_is_measured_again(made, product, capsys):
    session, original = made
    bad = product / "merged" / "d0002_P.npy"
    bad.unlink()
    code, out = verify_cli(product, capsys)
    assert code == 1 and f"{bad}: missing" in out
    index = run_process(session, product)
    assert [m["file"] for m in index["repaired"]["merged"]] == [str(bad)]
    assert_same_panorama(product, original)


# ------------------------------------------------------------------ stores written before checksums
def test_a_store_written_before_checksums_still_opens_and_resumes(tmp_path, monkeypatch):
    from omnispectral.mosaic import store as store_module

    def without_crc32c(name):
        from zarr.codecs import BloscCodec

        return (BloscCodec(cname="zstd", clevel=1, shuffle="shuffle", typesize=4),)

    monkeypatch.setattr(store_module, "_compressors", without_crc32c)
    old = PanoramaStore.create(tmp_path / "old.zarr", 32, 64, 6, 16, {}, {"a": 1})
    data = np.arange(16 * 16 * 6, dtype=np.float32).reshape(16, 16, 6)
    old.write_chunk(0, 0, 1, data, {"holes": 0})
    marker = old.path / "0" / ".done" / "0_1.json"  # a marker as written before: statistics only
    marker.write_text(json.dumps({"level": 0, "ty": 0, "tx": 1, "holes": 0}))
    monkeypatch.undo()

    store = PanoramaStore.open(tmp_path / "old.zarr")
    np.testing.assert_array_equal(store.read(0, slice(0, 16), slice(16, 32)), data)
    assert store.chunk_problems(0) == []  # nothing recorded: nothing to check
    resumed = PanoramaStore.create(tmp_path / "old.zarr", 32, 64, 6, 16, {}, {"a": 1})
    assert resumed.done_markers(0) == {(0, 1): {"level": 0, "ty": 0, "tx": 1, "holes": 0}}
