"""The option objects of ``process`` and ``mosaic``, the METHODS-style tables and the one progress type."""

from __future__ import annotations

import pytest

from omnispectral.errors import ConfigurationError
from omnispectral.mosaic.blending import BLENDS, blend_method
from omnispectral.mosaic.interp import KERNEL_RADIUS_PX, METHODS, interpolation
from omnispectral.mosaic.options import DEFAULT_TILE, MosaicOptions
from omnispectral.mosaic.tile import TILE_RENDERERS
from omnispectral.product.fingerprint import REGISTRATION_IDENTITY
from omnispectral.product.merge import RAW_ORDERS
from omnispectral.product.process import DEFAULT_INTERP, REGISTRATIONS, ProcessOptions
from omnispectral.product.sun_methods import SUN_METHODS
from omnispectral.progress import optional_progress, report_progress, under_stage


def test_the_tables_keep_the_method_names_in_their_order():
    assert list(METHODS) == ["linear", "cubic", "spline", "lanczos", "cubic-clamped"]
    assert KERNEL_RADIUS_PX == {"linear": 1, "cubic": 2, "spline": 2, "lanczos": 3, "cubic-clamped": 2}
    assert list(BLENDS) == ["linear", "multiband"] and set(TILE_RENDERERS) == set(BLENDS)
    assert list(REGISTRATIONS) == ["parallax", "paper"] and set(REGISTRATION_IDENTITY) == set(REGISTRATIONS)
    assert list(SUN_METHODS) == ["auto", "nd-bracket", "diffuse-reference", "sky-model", "none"]
    assert set(RAW_ORDERS) == {"merge-first", "demosaic-first"}


@pytest.mark.parametrize(("lookup", "name", "message"), [
    (interpolation, "bicubic", r"unknown interpolation 'bicubic'; expected one of linear, cubic, spline, lanczos"),
    (blend_method, "feather", r"unknown blend 'feather'; expected one of linear, multiband"),
])
def test_unknown_method_names_list_the_valid_ones(lookup, name, message):
    with pytest.raises(ConfigurationError, match=message):
        lookup(name)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"interp": "nearest"}, "unknown interpolation"), ({"blend": "max"}, "unknown blend"),
    ({"tile": 8}, "tile must be at least 16"), ({"width": 101}, "width must be an even number"),
])
def test_mosaic_options_are_validated_when_built(kwargs, message):
    with pytest.raises(ConfigurationError, match=message):
        MosaicOptions(**kwargs)


def test_mosaic_options_come_from_keywords_or_as_one_object():
    built = MosaicOptions.from_keywords(None, width=64, tile=32, interp="linear")
    assert built == MosaicOptions(width=64, tile=32, interp="linear")
    assert MosaicOptions.from_keywords(built, width=None, tile=DEFAULT_TILE) is built  # keywords at their defaults
    with pytest.raises(ConfigurationError, match=r"either options= or keywords.*tile"):
        MosaicOptions.from_keywords(built, tile=64)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"registration": "sift"}, "unknown registration 'sift'; expected one of parallax, paper"),
    ({"sun": "guess"}, "unknown sun method 'guess'; expected one of auto, nd-bracket"),
    ({"hdr_weight": "flat"}, "unknown weight 'flat'; expected one of triangle, noise"),
    ({"interp": "nearest"}, "unknown interpolation"), ({"tile": 4}, "tile must be at least 16"),
])
def test_process_options_are_validated_when_built(kwargs, message):
    with pytest.raises(ConfigurationError, match=message):
        ProcessOptions(**kwargs)


def test_process_options_give_the_mosaic_its_options():
    options = ProcessOptions(width=128, workers=2)
    assert options.interp == DEFAULT_INTERP and options.min_confidence is None
    mosaic = options.mosaic_options(b_predictor=None, overwrite=True)
    assert mosaic == MosaicOptions(width=128, tile=DEFAULT_TILE, interp=DEFAULT_INTERP, workers=2, overwrite=True)
    with pytest.raises(ConfigurationError, match=r"either options= or keywords.*registration"):
        ProcessOptions.from_keywords(options, registration="paper")


def test_the_progress_helpers():
    calls = []
    report_progress(None, "merge", 1, 2)  # nothing to report to
    report_progress(lambda *a: calls.append(a), "merge", 1, 2)
    under_stage(lambda *a: calls.append(a), "merge + register")("merge", 3, 4)
    assert calls == [("merge", 1, 2), ("merge + register", 3, 4)]
    assert under_stage(None, "x") is None and optional_progress(False) is None
