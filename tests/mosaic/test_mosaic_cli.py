"""``omnispectral mosaic``: the command line, and the raw-session path (HDR merge per direction, then stitching)."""

from __future__ import annotations

import datetime as dt
import json
import subprocess
import sys

import numpy as np
import pytest

from omnispectral.cli import main
from omnispectral.errors import InputFileError
from omnispectral.mosaic import PanoramaStore, mosaic
from omnispectral.product.process import DEFAULT_INTERP as PROCESS_INTERP  # the command's default
from omnispectral.rig import camera_model, load_preset
from omnispectral.sim.synthetic import six_band_panorama, write_synthetic_merged
from omnispectral.spectral.curves import DEFAULT_WAVELENGTH_NM

RIG = load_preset("small")


def flat_scene(rays):
    return six_band_panorama(np.broadcast_to(np.array([1.0, 2.0, 3.0], np.float32), (*rays.shape[:-1], 3)))


@pytest.fixture(scope="module")
def merged(tmp_path_factory):
    from omnispectral.capture.plan import direction_grid

    dirs = [(d.pan_deg, d.tilt_deg) for d in direction_grid(12, 3)]
    return write_synthetic_merged(tmp_path_factory.mktemp("cli") / "merged", flat_scene,
                                  {c: camera_model(RIG, c) for c in "AB"}, dirs)


def test_mosaic_command_json(merged, tmp_path, capsys):
    out = tmp_path / "pano.zarr"
    assert main(["mosaic", str(merged.path), "-o", str(out), "--width", "128", "--tile", "64", "--interp", "linear",
                 "--json", "--no-progress"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["width"] == 128 and summary["height"] == 64 and summary["holes_px"] == 0
    assert summary["tiles"] == summary["tiles_computed"] == 2 and summary["interp"] == "linear"
    np.testing.assert_allclose(PanoramaStore.open(out).read(0), np.broadcast_to([1, 2, 3, 2, 3, 1], (64, 128, 6)),
                               rtol=1e-6)
    # second run: everything is done already
    assert main(["mosaic", str(merged.path), "-o", str(out), "--width", "128", "--tile", "64", "--interp", "linear",
                 "--json", "--no-progress"]) == 0
    assert json.loads(capsys.readouterr().out)["tiles_skipped"] == 2


def test_mosaic_command_human_summary(merged, tmp_path):
    r = subprocess.run([sys.executable, "-m", "omnispectral.cli", "mosaic", str(merged.path), "-o",
                        str(tmp_path / "p.zarr"), "--width", "128", "--tile", "64"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    text = " ".join(r.stdout.split())
    assert "128 x 64 x 6" in text and "tiles: 2 computed" in text
    assert r.stderr == ""  # progress bars only when standard error is a terminal


def test_mosaic_command_bad_input_is_one_line(tmp_path):
    (tmp_path / "input").mkdir()
    r = subprocess.run([sys.executable, "-m", "omnispectral.cli", "mosaic", str(tmp_path / "input"), "-o",
                        str(tmp_path / "p.zarr")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "neither a capture session" in " ".join(r.stderr.split())
    assert "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "omnispectral.cli", "mosaic", "--help"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "--scheduler" in r.stdout and "--interp" in r.stdout


class SmoothSkyScene:
    """Spectral radiance ``a(ray) s1(λ) + b(ray) s2(λ)`` with smooth positive ``a``, ``b`` (at infinity)."""

    wavelength_nm = DEFAULT_WAVELENGTH_NM

    def __init__(self):
        wl = self.wavelength_nm
        self.s1 = (1.0 + 0.5 * np.sin(wl / 30.0)).astype(np.float32)
        self.s2 = np.exp(-((wl - 550.0) / 60.0) ** 2).astype(np.float32)

    def _ab(self, rays):
        x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
        return 1.0 + 0.3 * np.sin(2 * x) * np.cos(z), 0.5 + 0.2 * y

    def spectral_radiance(self, directions, origin_m=(0.0, 0.0, 0.0)):
        a, b = self._ab(np.asarray(directions))
        return (a[:, None] * self.s1 + b[:, None] * self.s2).astype(np.float32)

    def band_radiance(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0)):
        return self.spectral_radiance(directions, origin_m) @ sensitivity.T.astype(np.float32)

    def describe(self):
        return {"kind": "smooth-sky-test"}


@pytest.mark.slow
def test_mosaic_of_a_raw_session_matches_its_ground_truth(tmp_path):
    """Simulated capture (noise-free, 12 x 3 directions, 15 exposures) → merged per direction → panorama ≈ truth."""
    from omnispectral.sim.simulate import simulate_session

    session = tmp_path / "session"
    simulate_session(session, RIG, SmoothSkyScene(), start=dt.datetime(2026, 3, 21, 12, 0), noise=False,
                     ground_truth_width=256, progress=False)
    r = subprocess.run([sys.executable, "-m", "omnispectral.cli", "mosaic", str(session), "-o",
                        str(tmp_path / "p.zarr"), "--width", "256", "--tile", "64", "--json", "--no-progress"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["holes_px"] == 0 and (session / "merged" / "merged.json").is_file()
    meta = json.loads((session / "merged" / "merged.json").read_text())
    assert meta["complete"] and meta["dtype"] == "float16" and meta["session"]["kind"] == "simulation"
    truth = np.load(session / "ground_truth" / "bands.npy")
    pano = PanoramaStore.open(tmp_path / "p.zarr").read(0)
    rel = np.abs(pano - truth) / truth
    assert np.median(rel) < 2e-3 and np.percentile(rel, 99) < 1e-2  # 12-bit quantisation of the brackets
    attrs = PanoramaStore.open(tmp_path / "p.zarr").attrs()["omnispectral"]
    assert attrs["session"]["kind"] == "simulation" and attrs["rig"]["name"] == "small"
    # mosaicking again (the library takes the merged directions the command wrote, and the prior's predictor
    # of B's bands the command used) resumes the store; without the predictor it is another panorama
    from omnispectral.capture.session import Session
    from omnispectral.product.estimator import b_predictor, rig_estimator

    predictor = b_predictor(rig_estimator(Session.open(session).rig())[0])
    assert attrs["mosaic"]["b_predictor"] == predictor.to_dict()
    again = mosaic(session / "merged", tmp_path / "p.zarr", width=256, tile=64, interp=PROCESS_INTERP,
                   b_predictor=predictor)
    assert again["tiles_skipped"] == again["tiles"]
    with pytest.raises(InputFileError, match="other inputs or parameters"):
        mosaic(session / "merged", tmp_path / "p.zarr", width=256, tile=64, interp=PROCESS_INTERP)
