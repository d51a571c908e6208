"""The simulated rig: analytic checks of rendered frames, geometry, noise, ground truth, a whole session."""

from __future__ import annotations

import datetime as dt
import json

import numpy as np
import pytest

from omnispectral.capture.session import Session, dark_extensions
from omnispectral.imaging.geometry import ray_to_lonlat
from omnispectral.rig import camera_model, load_preset, rig_system
from omnispectral.sim.simulate import RigRenderer, sample_dn, simulate_session
from omnispectral.spectral.curves import DEFAULT_WAVELENGTH_NM
from omnispectral.spectral.noise import CMV2000


class SpotScene:
    """Uniform spectral background plus a bright disc of radius 2° at (lon 30°, lat 10°)."""

    wavelength_nm = DEFAULT_WAVELENGTH_NM

    def __init__(self):
        wl = self.wavelength_nm
        self.background = (0.5 + 0.3 * np.sin(wl / 40.0)).astype(np.float32)
        self.spot = (20.0 * np.exp(-((wl - 600.0) / 50.0) ** 2)).astype(np.float32)

    def _in_spot(self, directions):
        lon, lat = ray_to_lonlat(directions)
        return np.hypot(lon - 30.0, lat - 10.0) < 2.0

    def spectral_radiance(self, directions, origin_m=(0.0, 0.0, 0.0)):
        inside = self._in_spot(np.asarray(directions))
        return np.where(inside[:, None], self.spot, self.background).astype(np.float32)

    def band_radiance(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0)):
        return self.spectral_radiance(directions, origin_m) @ sensitivity.T.astype(np.float32)

    def describe(self):
        return {"kind": "spot-test"}

    def colorchecker_patches(self):
        return []


@pytest.fixture(scope="module")
def renderer():
    return RigRenderer(load_preset("small"), SpotScene())


def test_frame_values_match_the_analytic_integral(renderer):
    rig = renderer.rig
    t = rig.bracket.exposures_s[5]
    frame = renderer("A", -120.0, -30.0, t, np.random.default_rng(0))  # background only
    expected_dn = renderer.electrons_per_unit * (renderer.band_matrix("A") @ SpotScene().background) * t \
        / CMV2000.gain_e_per_dn
    valid = renderer.pixel_valid("A")
    mean = frame[valid].reshape(-1, 3).mean(axis=0)
    n = valid.sum()
    sigma_of_mean = np.sqrt(CMV2000.variance_dn2(expected_dn) / n)
    np.testing.assert_array_less(np.abs(mean - expected_dn), 5 * sigma_of_mean + 0.05)
    # the pixel-to-pixel spread is the noise model's
    np.testing.assert_allclose(frame[valid].reshape(-1, 3).std(axis=0), np.sqrt(CMV2000.variance_dn2(expected_dn)),
                               rtol=0.1)


def test_spot_lands_where_the_camera_model_says(renderer):
    m = renderer.models["A"]
    for pan, tilt in ((30.0, 10.0), (25.0, 5.0)):
        img = renderer.electrons_per_second("A", pan, tilt)[..., 0]
        ys, xs = np.nonzero(img > img.max() * 0.5)
        from omnispectral.imaging.geometry import lonlat_to_ray

        px, ok = m.world_to_pixel(lonlat_to_ray(30.0, 10.0)[None], pan, tilt)
        assert ok.all()
        assert abs(xs.mean() - px[0, 0]) < 0.6 and abs(ys.mean() - px[0, 1]) < 0.6


def test_portrait_mounting_swaps_the_fields_of_view(renderer):
    a = camera_model(renderer.rig, "A")
    assert a.mounting.roll_deg == 90.0 and a.hfov_deg == pytest.approx(95.0, abs=0.01)
    b = camera_model(renderer.rig, "B")
    assert b.mounting.baseline_mm == (60.0, 0.0, 0.0)
    assert rig_system(renderer.rig).band_names == ("A:R", "A:G", "A:B", "B:R", "B:G", "B:B")


def test_noise_sampler_matches_the_noise_model():
    """The fast float32 sampler has the statistics of SensorNoiseModel.sample_dn (exact Poisson, float64),
    including the bias of clipping at 0 DN for very dark pixels."""
    rng = np.random.default_rng(1)
    for mean_e in (5.0, 200.0, 9000.0):
        fast = sample_dn(np.full(200_000, mean_e, np.float32), CMV2000, rng).astype(np.float64)
        exact = CMV2000.sample_dn(np.full(200_000, mean_e), rng)
        assert fast.mean() == pytest.approx(exact.mean(), abs=0.02 + 0.001 * exact.mean())
        assert fast.var() == pytest.approx(exact.var(), rel=0.03)
    assert sample_dn(np.full(10, 1e9, np.float32), CMV2000, rng).max() == CMV2000.max_dn


@pytest.mark.slow
def test_simulated_session_with_ground_truth(tmp_path):
    from omnispectral.capture.session import verify_session

    rig = load_preset("small")
    out = simulate_session(tmp_path / "sim", rig, SpotScene(), start=dt.datetime(2026, 6, 21, 12, 0, tzinfo=dt.UTC),
                           ground_truth_width=256, progress=False)
    assert out["complete"] and verify_session(tmp_path / "sim")["complete"]
    gt = json.loads((tmp_path / "sim" / "ground_truth" / "ground_truth.json").read_text())
    bands = np.load(tmp_path / "sim" / "ground_truth" / "bands.npy")
    spectral = np.load(tmp_path / "sim" / "ground_truth" / "spectral.npy")
    matrix = np.load(tmp_path / "sim" / "ground_truth" / "system_matrix.npy")
    assert bands.shape == (128, 256, 6) and gt["bands"]["names"][3] == "B:R"
    np.testing.assert_allclose(spectral @ matrix.T, bands, rtol=1e-4)  # same grid at this width
    # a background pixel of a raw frame, divided by its exposure, estimates the ground-truth DN/s
    import tifffile

    background = bands[100, 10, :3]  # far from the spot
    k = next(i for i, t in enumerate(rig.bracket.exposures_s) if background.max() * t < 3000)  # unsaturated
    frame = tifffile.imread(tmp_path / "sim" / "frames" / "d0000" / f"A_e{k:02d}.tif").astype(np.float64)
    t = rig.bracket.exposures_s[k]
    valid = frame.sum(axis=2) > 0
    assert np.median(frame[valid], axis=0) / t == pytest.approx(background, rel=0.02)
    # the journal's simulated timestamps follow the timing model
    lines = (tmp_path / "sim" / "journal.jsonl").read_text().splitlines()
    last = dt.datetime.fromisoformat(json.loads(lines[-1])["timestamp"])
    assert (last - dt.datetime(2026, 6, 21, 12, 0, tzinfo=dt.UTC)).total_seconds() == pytest.approx(180, rel=0.05)


def _dark_frames(path) -> int:
    """Frames of a session's dark extensions (both cameras)."""
    s = Session.open(path)
    return len(s.cameras()) * sum(dark_extensions(s, s.plan()).values())


@pytest.mark.slow
def test_cli_simulate_procedural_scene_with_a_cube_and_verify(tmp_path, capsys):
    from omnispectral.cli import main

    rng = np.random.default_rng(0)
    wl = np.arange(400, 701, 10.0)
    cube = np.clip(0.2 + 0.6 * rng.random((12, 16, 1)) * np.exp(-((wl - 550) / 80) ** 2), 0, 1)
    np.savez(tmp_path / "cube.npz", cube=cube.astype(np.float32), wavelength_nm=wl)
    code = main(["simulate", "--preset", "small", "--time", "10:15", "--cube", str(tmp_path / "cube.npz"),
                 "--gt-width", "128", "--seed", "3", "-o", str(tmp_path / "s"), "--json"])
    out = json.loads(capsys.readouterr().out)
    # 1080 regular frames, one sun bracket (4 attenuated exposures x 2 cameras) holding the sun whole, and the
    # dark extension of the directions whose darkest pixels the bracket leaves noisy
    assert code == 0 and out["complete"] and out["n_written"] == 1080 + 8 + _dark_frames(tmp_path / "s")
    assert main(["session", "verify", str(tmp_path / "s")]) == 0
    meta = json.loads((tmp_path / "s" / "session.json").read_text())
    assert meta["kind"] == "simulation" and meta["simulation"]["seed"] == 3
    gt = json.loads((tmp_path / "s" / "ground_truth" / "ground_truth.json").read_text())
    assert len(gt["colorchecker_patches"]) == 24
    first = json.loads((tmp_path / "s" / "journal.jsonl").read_text().splitlines()[0])
    assert first["timestamp"].startswith("2017-06-21T10:15")


@pytest.mark.slow
def test_cli_timelapse_records_an_overrun_slot(tmp_path, capsys):
    from omnispectral.cli import main

    code = main(["timelapse", "--preset", "small", "--every", "2min", "--from", "09:00", "--to", "09:04",
                 "--gt-width", "64", "-o", str(tmp_path / "series"), "--json"])
    index = json.loads(capsys.readouterr().out)
    assert code == 0
    # each capture takes ~180 s of simulated time: 09:02 is skipped, 09:04 runs
    assert [e["status"] for e in index["slots"]] == ["complete", "skipped", "complete"]
    assert (tmp_path / "series" / "slot_0904" / "ground_truth" / "bands.npy").exists()


@pytest.mark.slow
def test_cli_capture_runs_the_devices_the_rig_names(tmp_path, capsys):
    from omnispectral.cli import main

    text = load_preset("small").toml_text
    (tmp_path / "rig.toml").write_text(text)
    assert main(["capture", "--rig", str(tmp_path / "rig.toml"), "--gt-width", "64", "-o", str(tmp_path / "s"),
                 "--json"]) == 0
    n_written = json.loads(capsys.readouterr().out)["n_written"]
    # the regular frames, the dark extension's and 1-3 sun brackets (4 exposures x 2 cameras)
    assert n_written - 1080 - _dark_frames(tmp_path / "s") in (8, 16, 24)
    # a second run resumes: nothing left to do
    assert main(["capture", "--rig", str(tmp_path / "rig.toml"), "-o", str(tmp_path / "s"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_already_done"] == n_written
    real = text.replace('driver = "simulated"\nmodel', 'driver = "merlin"\nmodel').replace('port = ""',
                                                                                         'port = "/dev/ttyUSB0"')
    (tmp_path / "real.toml").write_text(real)
    assert main(["capture", "--rig", str(tmp_path / "real.toml"), "-o", str(tmp_path / "r")]) == 2
    # a real head with simulated cameras cannot work: the simulated cameras render the simulated head's direction
    assert "simulated cameras render what the simulated head points at" in capsys.readouterr().err


def test_camera_rays_filter_a_fine_texture_over_their_footprint():
    """A frame of a texture finer than the rays (~6 × 6 texels per pixel): 2 × 2 rays per pixel that filter the
    texture over their share of the pixel give what 6 × 6 such rays give; 2 × 2 point samples miss it by ten
    times as much."""
    from omnispectral.sim.scenes import CubeOnWallScene, ProceduralOutdoorScene

    rng = np.random.default_rng(4)
    cube = (rng.uniform(0.05, 0.9, (240, 240, 3)) * rng.uniform(0.5, 1.0, (1, 1, 3))).astype(np.float32)
    base = ProceduralOutdoorScene()
    scene = CubeOnWallScene((cube, np.array([400.0, 550.0, 700.0])), base=base, lon_deg=-40.0, lat_deg=5.0)
    rig = load_preset("small")

    def frame(supersample, filtered=True):
        r = RigRenderer(rig, scene if filtered else _PointSampled(scene), noise=False, supersample=supersample)
        return r.electrons_per_second("A", -40.0, 0.0)

    on_panel = np.abs(frame(1) - RigRenderer(rig, base, noise=False, supersample=1).electrons_per_second(
        "A", -40.0, 0.0)).max(axis=-1) > 0
    inner = on_panel.copy()
    inner[1:-1, 1:-1] &= on_panel[:-2, 1:-1] & on_panel[2:, 1:-1] & on_panel[1:-1, :-2] & on_panel[1:-1, 2:]
    inner[[0, -1]] = False
    inner[:, [0, -1]] = False
    assert inner.sum() > 100
    reference = frame(6)

    def median_error(x):
        return float(np.median(np.abs(x / reference - 1)[inner]))

    assert median_error(frame(2)) < 0.005
    assert median_error(frame(2, filtered=False)) > 10 * median_error(frame(2))


class _PointSampled:
    """A scene seen through renderers that do not pass ray footprints (point sampling)."""

    def __init__(self, scene):
        self.scene = scene
        self.wavelength_nm = scene.wavelength_nm

    def __getattr__(self, name):
        if name == "ray_footprint":
            return False
        return getattr(self.scene, name)
