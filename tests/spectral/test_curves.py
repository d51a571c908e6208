from __future__ import annotations

import numpy as np
import pytest

from omnispectral.errors import InputFileError
from omnispectral.spectral.curves import SpectralSet, read_spectral_csv, write_spectral_csv
from omnispectral.spectral.library import load_filter, load_reflectances


def write(tmp_path, text, name="c.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_read_and_resample_matches_numpy_interp(tmp_path):
    p = write(tmp_path, "# a comment\nwavelength_nm,f1,f2\n380,0.1,0.5\n500,0.4,0.5\n720,0.9,0.2\n")
    s = read_spectral_csv(p, "transmittance")
    assert s.names == ("f1", "f2")
    r = s.resample()
    assert r.values.shape == (2, 61)
    np.testing.assert_allclose(r.values[0], np.interp(r.wavelength_nm, [380, 500, 720], [0.1, 0.4, 0.9]))


def test_percent_detected_and_converted(tmp_path):
    p = write(tmp_path, "wavelength_nm,34A\n400,0\n550,40\n700,90\n")
    s = read_spectral_csv(p, "transmittance")
    assert s.values.max() == pytest.approx(0.9)
    assert any("percent" in n for n in s.notes)


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        ("wavelength_nm,a\n400,0.1\n500,0.2\n450,0.3\n", 4, "not strictly increasing"),
        ("wavelength_nm,a\n400,0.1\n500,nan\n", 3, "NaN"),
        ("wavelength_nm,a\n400,0.1\n500,-0.4\n", 3, "negative"),
        ("wavelength_nm,a,b\n400,0.1,0.2\n500,0.3\n", 3, "2 fields, expected 3"),
        ("wavelength_nm,a\n400,0.1\n500,abc\n", 3, "not a number"),
        ("lambda,a\n400,0.1\n", 1, "expected 'wavelength_nm'"),
    ],
)
def test_malformed_csv_names_file_line_and_problem(tmp_path, text, line, words):
    p = write(tmp_path, text)
    with pytest.raises(InputFileError) as exc:
        read_spectral_csv(p, "transmittance")
    msg = str(exc.value)
    assert str(p) in msg and f"line {line}" in msg and words in msg


def test_range_not_covering_grid_is_an_error(tmp_path):
    p = write(tmp_path, "wavelength_nm,a\n420,0.1\n700,0.2\n")
    s = read_spectral_csv(p, "transmittance")
    with pytest.raises(InputFileError, match=r"420-700 nm does not cover the grid 400-700 nm"):
        s.resample()


def test_missing_file_is_named(tmp_path):
    with pytest.raises(InputFileError, match="file not found"):
        read_spectral_csv(tmp_path / "nope.csv", "illuminant")


def test_fraction_above_one_refused_when_unit_stated(tmp_path):
    p = write(tmp_path, "wavelength_nm,a\n400,0.1\n700,40\n")
    with pytest.raises(InputFileError, match="exceeds 1"):
        read_spectral_csv(p, "reflectance", percent=False)


def test_tiny_negative_noise_is_clipped(tmp_path):
    p = write(tmp_path, "wavelength_nm,a\n400,-0.0001\n700,0.5\n")
    s = read_spectral_csv(p, "sensitivity")
    assert s.values.min() == 0.0 and any("clipped" in n for n in s.notes)


def test_write_read_round_trip(tmp_path):
    s = load_reflectances("colorchecker").resample()
    p = write_spectral_csv(s, tmp_path / "cc.csv", comment="ColorChecker")
    back = read_spectral_csv(p, "reflectance")
    np.testing.assert_allclose(back.values, s.values, rtol=1e-5, atol=1e-6)
    assert back.names == s.names
    assert not list(tmp_path.glob(".cc.csv.*")), "temporary file left behind"


def test_shipped_34a_matches_shared_table(shared_data):
    table = read_spectral_csv(shared_data / "filter_transmittance" / "wratten_visible_400-700nm_10nm_percent.csv",
                              "transmittance").select(["34A"])
    shipped = load_filter("wratten-34a")
    np.testing.assert_allclose(shipped.values, table.values)
    # published facts: blue pass band peaking ~70 % at 430 nm, red band above 630 nm
    assert shipped.values[0, 3] == pytest.approx(0.697)


def test_sprague_resampling_of_smooth_data_is_close_to_linear():
    wl = np.arange(400, 701, 10.0)
    s = SpectralSet(wl, np.exp(-0.5 * ((wl - 550) / 60) ** 2)[None], ["g"], "reflectance", "test")
    lin = s.resample(method="linear").values
    spr = s.resample(method="sprague").values
    truth = np.exp(-0.5 * ((np.arange(400, 701, 5.0) - 550) / 60) ** 2)
    assert np.abs(spr - truth).max() < np.abs(lin - truth).max()
