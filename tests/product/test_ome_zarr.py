"""The panorama store as other tools read it: OME-Zarr 0.5 (ome-zarr-models, ome-zarr's reader), xarray."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from omnispectral.errors import InputFileError
from omnispectral.mosaic.store import PanoramaStore, box_average_2x2, pyramid_shapes
from omnispectral.product.layout import write_band_product

BANDS = ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"]
H, W, TILE = 64, 128, 32


@pytest.fixture(scope="module")
def bands():
    rng = np.random.default_rng(14)
    b = rng.uniform(0.0, 1e4, (H, W, 6)).astype(np.float32)
    b[:3, :5] = np.nan  # uncovered pixels stay NaN
    return b


@pytest.fixture(scope="module")
def product(tmp_path_factory, bands):
    root = tmp_path_factory.mktemp("ome") / "product"
    big = {"bands": BANDS, "units": "DN per second of exposure", "estimator": {"blob": list(range(20000))}}
    write_band_product(root, bands, {"bands": BANDS, "units": "DN/s"}, attrs=big, tile=TILE)
    return root


def test_store_is_valid_ome_zarr_0_5_with_small_root_attributes(product):
    import zarr
    pytest.importorskip("ome_zarr_models", reason="ome-zarr-models is not installed (pip install 'omnispectral[test]')")
    from ome_zarr_models.v05.image import Image

    path = product / "panorama.zarr"
    image = Image.from_zarr(zarr.open_group(str(path), mode="r"))  # raises on any spec violation
    ome = image.attributes.ome
    assert ome.version == "0.5"
    ms = ome.multiscales[0]
    assert [(a.name, a.type) for a in ms.axes] == [("c", "channel"), ("y", "space"), ("x", "space")]
    assert [d.path for d in ms.datasets] == ["0", "1", "2"]
    # the bands' names as OME channel labels (what napari and ome-zarr show)
    root = json.loads((path / "zarr.json").read_text())["attributes"]["ome"]
    assert [c["label"] for c in root["omero"]["channels"]] == BANDS
    for k, ds in enumerate(ms.datasets):
        arr = zarr.open_array(str(path / ds.path), mode="r")
        assert arr.metadata.dimension_names == ("c", "y", "x")
        assert arr.shape == (6, *pyramid_shapes(H, W, TILE)[k])
        scale, translation = ds.coordinateTransformations
        step = 180.0 * 2 ** k / H
        assert scale.scale == [1.0, step, 360.0 * 2 ** k / W] and step == 360.0 * 2 ** k / W
        assert translation.translation == [0.0, step / 2, -180.0 + step / 2]  # pixel centres
    # the big metadata (here a 20000-element estimator) lives in its own group, not in the image's zarr.json
    root_bytes = (path / "zarr.json").stat().st_size
    assert root_bytes < 6000  # the OME metadata with six channel labels, not the estimator
    meta = json.loads((path / "omnispectral" / "zarr.json").read_text())
    assert meta["node_type"] == "group" and len(meta["attributes"]["omnispectral"]["estimator"]["blob"]) == 20000
    store = PanoramaStore.open(path)
    assert store.attrs()["omnispectral"]["estimator"]["blob"][-1] == 19999
    store.update_attrs({"omnispectral": {**store.attrs()["omnispectral"], "estimator": {"blob": [1]}}})
    assert store.attrs()["omnispectral"]["estimator"] == {"blob": [1]}
    assert (path / "zarr.json").stat().st_size == root_bytes


def test_ome_zarr_reader_gives_every_level_and_the_pixel_centres(product, bands):
    pytest.importorskip("ome_zarr", reason="ome-zarr is not installed (pip install 'omnispectral[test]')")
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Multiscales, Reader

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning about the layout or the foreign metadata group
        nodes = list(Reader(parse_url(str(product / "panorama.zarr")))())
    node = next(n for n in nodes if n.load(Multiscales))
    assert len(node.data) == 3
    expected = bands
    for k, level in enumerate(node.data):
        got = np.moveaxis(np.asarray(level), 0, -1)
        if k:
            expected = box_average_2x2(expected, pyramid_shapes(H, W, TILE)[k])
        np.testing.assert_allclose(got, expected, rtol=1e-6, equal_nan=True)
    # pixel (col, row) of level 1 through the metadata's scale and translation = docs/product.md's formula
    scale, translation = node.metadata["coordinateTransformations"][1]
    col, row = 17, 5
    lon = translation["translation"][2] + col * scale["scale"][2]
    colat = translation["translation"][1] + row * scale["scale"][1]
    w1, h1 = W // 2, H // 2
    assert lon == pytest.approx((col + 0.5) / w1 * 360 - 180)
    assert 90 - colat == pytest.approx(90 - (row + 0.5) / h1 * 180)


def test_xarray_reads_level0_with_lat_lon_band(product, bands):
    import xarray as xr

    store = PanoramaStore.open(product / "panorama.zarr")
    da = store.to_xarray(0)
    assert da.dims == ("band", "lat", "lon") and list(da.band.values) == BANDS
    # a direction picked by coordinates is the pixel the equirectangular formula names
    lon, lat = 33.0, -20.0
    col, row = int((lon + 180) / 360 * W), int((90 - lat) / 180 * H)
    np.testing.assert_array_equal(da.sel(lon=lon, lat=lat, method="nearest").values, bands[row, col])
    np.testing.assert_array_equal(da.sel(band="B:G").values, bands[..., 4])
    # the plain-xarray recipe of docs/product.md: one level of the group, the others dropped
    ds = xr.open_dataset(product / "panorama.zarr", engine="zarr", drop_variables=["1", "2"], consolidated=False)
    np.testing.assert_array_equal(np.moveaxis(ds["0"].values, 0, -1), bands)


def _legacy_store(path, bands):
    """A panorama written by format 1 (the first format): (y, x, band) arrays, everything in zarr.json."""
    import zarr

    shapes = pyramid_shapes(H, W, TILE)
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    level = bands
    for k, (h, w) in enumerate(shapes):
        if k:
            level = box_average_2x2(level, (h, w))
        group.create_array(str(k), data=level, chunks=(TILE, TILE, 6), dimension_names=("y", "x", "band"))
    group.attrs.update({"omnispectral": {"format": "omnispectral-panorama", "format_version": 1, "tile": TILE,
                                         "levels": [list(s) for s in shapes], "bands": BANDS, "units": "DN/s"},
                        "multiscales": [], "fingerprint": {"old": True}})


def test_format1_stores_are_still_read_and_resuming_them_is_refused(tmp_path, bands):
    path = tmp_path / "old.zarr"
    _legacy_store(path, bands)
    store = PanoramaStore.open(path)
    assert store.format_version == 1 and store.n_bands == 6
    np.testing.assert_array_equal(store.read(0, slice(10, 20), slice(30, 50)), bands[10:20, 30:50])
    assert store.array(1).shape == (H // 2, W // 2, 6)
    np.testing.assert_array_equal(store.to_xarray(0).sel(band="A:B").values, bands[..., 2])
    assert store.attrs()["fingerprint"] == {"old": True}
    with pytest.raises(InputFileError, match=r"older omnispectral \(panorama format 1.*--overwrite"):
        PanoramaStore.create(path, H, W, 6, TILE, {}, fingerprint={"old": True})
    new = PanoramaStore.create(path, H, W, 6, TILE, {"bands": BANDS}, fingerprint={"new": 1}, overwrite=True)
    assert new.format_version == 2 and PanoramaStore.open(path).array(0).zarr.shape == (6, H, W)


def test_napari_reader_shows_every_band_by_name_with_its_geometry_and_a_window_from_the_data(product, bands):
    """What napari shows when it opens the store through napari-ome-zarr (README: `napari product/panorama.zarr`):
    one image layer split on the channel axis, layer names ending in the band names, every pyramid level, the
    pixel-centre geometry in degrees, the values as written and display windows that fit the data (the
    99.5th percentile of each band, not a fixed 1e6 DN/s)."""
    pytest.importorskip("napari_ome_zarr", reason="napari-ome-zarr is not installed (pip install 'omnispectral[test]')")
    from napari_ome_zarr import napari_get_reader

    path = str(product / "panorama.zarr")
    reader = napari_get_reader(path)
    assert reader is not None
    (data, kwargs, kind), = reader(path)
    assert kind == "image" and kwargs["channel_axis"] == 0
    assert [name.rsplit(": ", 1)[-1] for name in kwargs["name"]] == BANDS
    assert [tuple(d.shape) for d in data] == [(6, *s) for s in pyramid_shapes(H, W, TILE)]
    np.testing.assert_array_equal(np.asarray(data[0]), np.moveaxis(bands, 2, 0))  # NaN where uncovered, too
    assert list(kwargs["scale"]) == [180.0 / H, 360.0 / W]
    coarse = np.asarray(data[-1])
    for k, (start, end) in enumerate(kwargs["contrast_limits"]):
        assert start == 0.0
        assert end == pytest.approx(np.nanpercentile(coarse[k], 99.5), rel=1e-6)
        assert end < np.nanmax(bands[..., k])
