"""Nothing the user owns is deleted: outputs replace only what omnispectral wrote."""

from __future__ import annotations

import json

import pytest

from omnispectral.errors import InputFileError
from omnispectral.fingerprint import check_merged
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.ownership import written_by_omnispectral


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


def _main(argv):
    from omnispectral.cli import main

    return main([str(a) for a in argv])


def test_an_output_that_is_or_lies_inside_an_input_is_refused(tmp_path, capsys):
    """``calibrate rig S -o S/rig.toml``, ``mosaic S -o S``, ``export P -o P/product.json``: one line, exit 2,
    the input untouched (was: the session's rig replaced, or the session deleted with ``--overwrite``)."""
    session = tmp_path / "session"
    session.mkdir()
    (session / "rig.toml").write_text("the session's rig")
    product = tmp_path / "product"
    product.mkdir()
    (product / "product.json").write_text('{"format": "omnispectral-product"}')
    for argv in (["calibrate", "rig", session, "-o", session / "rig.toml"],
                 ["mosaic", session, "-o", session, "--overwrite"],
                 ["mosaic", session, "-o", session / "pano.zarr"],
                 ["export", product, "--format", "png", "-o", product / "product.json"]):
        assert _main(argv) == 2
        err = capsys.readouterr().err
        assert "input" in err and len(err.strip().splitlines()) == 1, err
    assert (session / "rig.toml").read_text() == "the session's rig"
    assert (product / "product.json").read_text() == '{"format": "omnispectral-product"}'


def test_directory_outputs_go_only_into_new_empty_or_our_directories(tmp_path):
    """``process``, ``render``, ``relight``, ``render-series``, the demo and chessboard views refuse a directory
    of the user's (nothing replaced), and take a new one, an empty one, or one they wrote before."""
    from omnispectral.ownership import OUTPUT_MARKER, claim_output_directory

    mine = tmp_path / "documents"
    (mine / "A").mkdir(parents=True)
    (mine / "report").mkdir()
    (mine / "report" / "report.html").write_text("the user's report")
    (mine / "A" / "view_00.png").write_bytes(b"the user's photo")
    for command in ("process", "render", "relight", "demo", "calibration views"):
        with pytest.raises(InputFileError, match="omnispectral did not write"):
            claim_output_directory(mine, command)
    assert (mine / "report" / "report.html").read_text() == "the user's report"
    assert not (mine / OUTPUT_MARKER).exists()
    fresh = claim_output_directory(tmp_path / "new" / "out", "render")
    assert (fresh / OUTPUT_MARKER).is_file()
    (fresh / "render.png").write_bytes(b"ours")
    assert claim_output_directory(fresh, "render") == fresh  # a rerun
    empty = tmp_path / "empty"
    empty.mkdir()
    claim_output_directory(empty, "process")
    legacy = tmp_path / "legacy"  # a product written before the marker existed
    legacy.mkdir()
    (legacy / "product.json").write_text('{"format": "omnispectral-product"}')
    claim_output_directory(legacy, "process")
    with pytest.raises(InputFileError, match="is a file"):
        claim_output_directory(legacy / "product.json", "process")


def _band_product(root):
    import numpy as np

    from omnispectral.product.estimator import estimator_params
    from omnispectral.product.layout import write_band_product
    from omnispectral.rig import load_preset

    bands = np.full((32, 64, 6), 100.0, np.float32)
    write_band_product(root, bands, {"bands": ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"], "units": "DN/s",
                                     "estimator": {"params": estimator_params(load_preset("small"))}}, tile=32)
    return root


def test_commands_refuse_a_users_directory_before_writing(tmp_path, capsys):
    """Through the command line: ``process`` into a directory of the user's, ``simulate-chessboard`` into a
    folder holding the user's images (was: ``clear_views`` deleted them), ``render``/``relight`` into the user's
    folder — exit 1, one line naming it, every file kept."""
    mine = tmp_path / "documents"
    (mine / "A").mkdir(parents=True)
    (mine / "A" / "photo.png").write_bytes(b"the user's photo")
    (mine / "report.html").write_text("the user's")
    session = tmp_path / "session"
    session.mkdir()
    product = _band_product(tmp_path / "product")
    for argv in (["process", session, "-o", mine],
                 ["simulate-chessboard", "--preset", "small", "-o", mine, "--views", "1"],
                 ["relight", product, "--white=0,0,1", "--to", "A", "-o", mine]):
        assert _main(argv) == 1
        err = capsys.readouterr().err
        assert str(mine) in err and "did not write" in err and len(err.strip().splitlines()) == 1, err
    assert (mine / "A" / "photo.png").read_bytes() == b"the user's photo"
    assert (mine / "report.html").read_text() == "the user's"


def test_overwrite_keeps_a_users_file_inside_our_trees(tmp_path):
    """``process --overwrite`` rebuilding ``merged/`` and ``panorama.zarr/`` stops, before removing anything,
    at a file the user put inside them (was: deleted with the tree)."""
    merged, pano, index = tmp_path / "merged", tmp_path / "panorama.zarr", tmp_path / "product.json"
    check_merged(merged, {"a": 1})
    (merged / "d0000_A.npy").write_bytes(b"ours")
    (merged / "my notes.txt").write_text("the user's")
    _store(pano)
    index.write_text(json.dumps({"format": "omnispectral-product"}))
    with pytest.raises(InputFileError, match=r"my notes\.txt.*did not write"):
        check_merged(merged, {"a": 2}, overwrite=True, dependents=(pano, index))
    assert (merged / "d0000_A.npy").exists() and pano.exists() and index.exists()
    (merged / "my notes.txt").unlink()
    (pano / "0" / "keep.csv").write_text("the user's table")
    with pytest.raises(InputFileError, match=r"keep\.csv"):
        check_merged(merged, {"a": 2}, overwrite=True, dependents=(pano, index))
    with pytest.raises(InputFileError, match=r"keep\.csv"):
        PanoramaStore.create(pano, 16, 32, 6, 16, {}, {"inputs": 2}, overwrite=True)
    assert (pano / "0" / "keep.csv").read_text() == "the user's table" and (merged / "d0000_A.npy").exists()
    (pano / "0" / "keep.csv").unlink()
    assert check_merged(merged, {"a": 2}, overwrite=True, dependents=(pano, index)) == "overwritten"
    assert not pano.exists() and not (merged / "d0000_A.npy").exists()


def test_mosaic_waits_for_the_products_lock(tmp_path):
    """``mosaic … -o PRODUCT/panorama.zarr`` while ``process`` holds the product (another process): refused
    naming the holder (was: written beside the running process)."""
    import subprocess
    import sys

    from omnispectral.locking import directory_lock

    product = tmp_path / "product"
    code = ("from omnispectral.mosaic.engine import mosaic\n"
            "from omnispectral.locking import LockedError\n"
            f"try:\n    mosaic({str(tmp_path / 'missing')!r}, {str(product / 'panorama.zarr')!r})\n"
            "except LockedError as e:\n    print('locked', e)\n")
    with directory_lock(product, "process"):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stdout.startswith("locked") and "process" in out.stdout, out.stdout + out.stderr
