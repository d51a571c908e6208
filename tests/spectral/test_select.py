from __future__ import annotations

import pytest

from omnispectral.errors import InputFileError
from omnispectral.spectral.curves import read_spectral_csv, write_spectral_csv
from omnispectral.spectral.evaluate import Protocol, evaluate_system
from omnispectral.spectral.select import select_filters
from omnispectral.spectral.system import six_band_system


@pytest.fixture
def small_table(shared_data, tmp_path):
    table = read_spectral_csv(shared_data / "filter_transmittance" / "wratten_visible_400-700nm_10nm_percent.csv",
                              "transmittance")
    sub = table.select(["34A", "47", "58", "25", "80A", "85", "36", "9"])
    path = tmp_path / "cands.csv"
    # write back in percent, as Kodak publishes
    from omnispectral.spectral.curves import SpectralSet

    write_spectral_csv(SpectralSet(sub.wavelength_nm, sub.values * 100, sub.names, "transmittance", "x"), path)
    return path


def test_select_scores_all_pairs_and_ranks_reference_consistently(small_table):
    r = select_filters(small_table, top=3)
    assert r["n_pairs"] == 28 and r["candidates"]["unit"] == "percent"
    nrmses = [row["nrmse"] for row in r["top"]]
    assert nrmses == sorted(nrmses)
    ref = r["reference"]
    assert ref["filter_a"] == "Wratten 34A"
    # the pair scores agree with the evaluation protocol run on its own (noise-free, same sigma^2)
    same = evaluate_system(six_band_system(), Protocol(mixture=False, noise=None, sigma2=ref["sigma2"]))
    assert ref["nrmse"] == pytest.approx(same["nrmse"], rel=1e-6)
    assert ref["delta_e_ab"] == pytest.approx(same["delta_e_ab"], rel=1e-6)
    best = r["top"][0]
    best_eval = evaluate_system(six_band_system(filters=(str(_one(small_table, best["filter_a"])),
                                                         str(_one(small_table, best["filter_b"])))),
                                Protocol(mixture=False, noise=None, sigma2=best["sigma2"]))
    assert best["nrmse"] == pytest.approx(best_eval["nrmse"], rel=1e-6)


def _one(table_path, name):
    s = read_spectral_csv(table_path, "transmittance").select([name])
    out = table_path.parent / f"{name}.csv"
    write_spectral_csv(s, out)
    return out


@pytest.mark.slow
def test_full_wratten_table_finds_pairs_better_than_reference(shared_data):
    r = select_filters(shared_data / "filter_transmittance" / "wratten_visible_400-700nm_10nm_percent.csv", top=5)
    assert r["n_pairs"] == 127 * 126 // 2
    assert r["top"][0]["nrmse"] <= r["reference"]["nrmse"]
    assert 1 <= r["reference"]["rank"] <= r["n_pairs"] + 1


def test_bad_candidate_table(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("wavelength_nm,a,b\n400,10,20\n500,30\n")
    with pytest.raises(InputFileError, match="line 3"):
        select_filters(p)
