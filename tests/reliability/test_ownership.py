"""Nothing the user owns is deleted: outputs replace only what omnispectral wrote."""

from __future__ import annotations

import json

import pytest

from omnispectral.errors import InputFileError
from omnispectral.fingerprint import check_merged, written_by_omnispectral
from omnispectral.mosaic.store import PanoramaStore


def _store(path):
    return PanoramaStore.create(path, 16, 32, 6, 16, {"bands": ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"]},
                                {"inputs": 1})


def test_a_directory_that_is_not_a_store_is_never_deleted_even_with_overwrite(tmp_path):
    mine = tmp_path / "photos"
    mine.mkdir()
    (mine / "holiday.jpg").write_bytes(b"\xff\xd8 not ours")
    for overwrite in (False, True):
        with pytest.raises(InputFileError, match="not a panorama store"):
            PanoramaStore.create(mine, 16, 32, 6, 16, {}, {"x": 1}, overwrite=overwrite)
    assert (mine / "holiday.jpg").read_bytes() == b"\xff\xd8 not ours"
    store = _store(tmp_path / "pano.zarr")  # a store of ours is replaced with overwrite
    assert written_by_omnispectral(store.path)
    PanoramaStore.create(store.path, 16, 32, 6, 16, {}, {"inputs": 2}, overwrite=True)


def test_process_overwrite_removes_nothing_it_did_not_write(tmp_path):
    merged, pano, index = tmp_path / "merged", tmp_path / "panorama.zarr", tmp_path / "product.json"
    merged.mkdir()
    (merged / "notes.txt").write_text("the user's")  # a folder named like ours, not ours
    for overwrite in (False, True):
        with pytest.raises(InputFileError, match="not written by omnispectral"):
            check_merged(merged, {"a": 1}, overwrite=overwrite, dependents=(pano, index))
    assert (merged / "notes.txt").read_text() == "the user's"
    # ours (a fingerprint of other inputs): replaced with overwrite, with the products made from it ...
    (merged / "notes.txt").unlink()
    check_merged(merged, {"a": 1})
    _store(pano)
    index.write_text(json.dumps({"format": "omnispectral-product"}))
    assert check_merged(merged, {"a": 2}, overwrite=True, dependents=(pano, index)) == "overwritten"
    assert not pano.exists() and not index.exists()
    # ... but a product.json the user wrote stops it before anything is removed
    index.write_text(json.dumps({"my": "data"}))
    with pytest.raises(InputFileError, match=r"product\.json"):
        check_merged(merged, {"a": 3}, overwrite=True, dependents=(pano, index))
    assert json.loads(index.read_text()) == {"my": "data"} and (merged / "fingerprint.json").exists()
