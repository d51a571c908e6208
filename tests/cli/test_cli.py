from __future__ import annotations

import json
import subprocess
import sys

import pytest

from omnispectral.cli import main


def run(*args):
    return subprocess.run([sys.executable, "-m", "omnispectral.cli", *args], capture_output=True, text=True,
                          timeout=120)


@pytest.mark.parametrize("args", [[], ["spectral"], ["spectral", "evaluate"], ["spectral", "select-filters"],
                                  ["spectral", "list"], ["calibrate", "rig"], ["simulate-chessboard"]])
def test_help_everywhere(args):
    r = run(*args, "--help")
    assert r.returncode == 0 and "usage:" in r.stdout


def test_evaluate_json(tmp_path, capsys):
    plot = tmp_path / "fig9.png"
    assert main(["spectral", "evaluate", "--json", "--plot", str(plot), "--json-out", str(tmp_path / "r.json")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_targets"] == 24
    assert out["six_band"]["nrmse"] <= 0.0148 and out["six_band"]["delta_e_ab"] <= 1.49
    assert {"nrmse", "delta_e_ab", "delta_e_2000"} <= set(out["rgb"])
    assert "definition" in out
    assert plot.stat().st_size > 10_000 and plot.read_bytes()[:4] == b"\x89PNG"
    assert json.loads((tmp_path / "r.json").read_text())["six_band"]["nrmse"] == out["six_band"]["nrmse"]


def test_evaluate_human_table(capsys):
    assert main(["spectral", "evaluate", "--plot", "none", "--estimator", "pooled"]) == 0
    text = capsys.readouterr().out
    assert "0.0148" in text and "6.12" in text and "unit L2 norm" in text and "stand-in" in text


def test_bad_camera_csv_is_a_clear_error(tmp_path):
    bad = tmp_path / "cam.csv"
    bad.write_text("wavelength_nm,R,G,B\n400,0.1,0.2,0.3\n390,0.1,0.2,0.3\n")
    r = run("spectral", "evaluate", "--camera", str(bad), "--plot", "none")
    assert r.returncode == 1
    assert str(bad) in r.stderr and "line 3" in r.stderr and "Traceback" not in r.stderr


def test_unknown_illuminant_is_a_clear_error():
    r = run("spectral", "evaluate", "--illuminant", "moonlight", "--plot", "none")
    assert r.returncode == 2 and "unknown illuminant 'moonlight'" in r.stderr


def test_list_json(capsys):
    assert main(["spectral", "list", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert "Nikon 5100 (NPL)" in data["cameras"] and "wratten-34a" in data["filters"]


def test_user_prior_sets(tmp_path, capsys):
    from omnispectral.spectral.curves import write_spectral_csv
    from omnispectral.spectral.library import load_reflectances

    mine = write_spectral_csv(load_reflectances("vrhel-dupont"), tmp_path / "mine.csv")
    assert main(["spectral", "evaluate", "--json", "--plot", "none", "--prior-set", str(mine),
                 "--prior-illuminant", "D65", "--prior-illuminant", "A"]) == 0
    out = json.loads(capsys.readouterr().out)
    prior = out["six_band"]["prior"]
    assert prior["reflectance_sets"] == [str(mine)] and prior["illuminants"] == ["D65", "A"]
    assert prior["n_reflectances"] + prior["n_excluded_as_held_out"] == 120


def test_evaluate_writes_no_plot_unless_asked(tmp_path, monkeypatch, capsys):
    """``spectral evaluate`` without ``--plot`` leaves the working directory as it was."""
    monkeypatch.chdir(tmp_path)
    assert main(["spectral", "evaluate", "--noise", "off", "--estimator", "pooled"]) == 0
    assert list(tmp_path.iterdir()) == [] and "Plot of" not in capsys.readouterr().out
