"""The dark extension: exposures of 2, 4, … times the bracket's longest where it leaves the darkest pixels noisy,
shot by the capture loop, resumed, verified, recorded in the dark frames and merged by processing."""

from __future__ import annotations

import datetime as dt
import json
import math
from dataclasses import replace

import numpy as np
import pytest

from omnispectral.capture.darks import load_darks, record_darks
from omnispectral.capture.plan import Plan, make_plan
from omnispectral.capture.run import RetryPolicy, dark_exposures_needed, darkest_signal_dn, run_capture
from omnispectral.capture.session import Session, bracket_indices, dark_extensions, verify_session
from omnispectral.cli.simulate import _print_exposures_set_otherwise
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.product.merge import RawSettings, merge_direction
from omnispectral.rig import DARK_EXPOSURE_BASE, load_preset, rig_from_dict, rig_toml
from omnispectral.sim.devices import CameraFaults, FakeClock, SimulatedCamera, SimulatedHead
from omnispectral.sim.simulate import simulated_dark_cameras
from omnispectral.spectral.noise import CMV2000

SHAPE = (30, 40, 3)
START = dt.datetime(2026, 3, 21, 6, 30, tzinfo=dt.UTC)


@pytest.mark.parametrize("snr", [3.0, 40.0, 150.0])
def test_the_signal_for_a_signal_to_noise_ratio_gives_that_ratio(snr):
    dn = CMV2000.dn_for_snr(snr)
    assert dn / math.sqrt(CMV2000.variance_dn2(dn)) == pytest.approx(snr, rel=1e-12)


def _frame(darkest_dn: float, fraction: float = 0.05, channel: int = 1) -> np.ndarray:
    """A bright frame whose ``fraction`` of pixels are dark in one channel only."""
    f = np.full(SHAPE, 3000, np.uint16)
    f.reshape(-1, 3)[: int(fraction * f.shape[0] * f.shape[1]), channel] = darkest_dn
    return f


def test_the_extension_doubles_the_darkest_signal_up_to_the_wanted_one():
    rig = load_preset("small")
    dark = make_plan(rig).dark_extension
    assert dark["exposures_s"] == pytest.approx([0.504, 1.008])
    wanted = rig.camera_a.noise_model().dn_for_snr(dark["snr"])  # 532 DN for the CMV2000 at SNR 40
    assert wanted == pytest.approx(532, abs=1)
    bright = _frame(3000)
    cases = {math.ceil(wanted): 0, wanted * 0.99: 1, wanted / 2.01: 2, wanted / 3: 2, 0: 2, 3000: 0}
    for dn, n in cases.items():
        frame = _frame(round(dn))
        assert darkest_signal_dn(frame, dark["percentile"]) == pytest.approx(round(dn))
        assert dark_exposures_needed({"A": frame, "B": bright}, rig, dark) == n, dn
        assert dark_exposures_needed({"A": bright, "B": frame}, rig, dark) == n, dn  # the darker camera decides
    # 0.5 % of the pixels dark: below the 1st percentile, not metered
    assert dark_exposures_needed({"A": _frame(10, fraction=0.005)}, rig, dark) == 0
    # the black level is no signal
    black = replace(rig, cameras={**rig.cameras, "A": replace(rig.camera_a, black_level_dn=200.0)})
    assert dark_exposures_needed({"A": _frame(round(wanted) + 100)}, black, dark) == 1


def test_rig_and_plan_carry_the_extension(tmp_path):
    import tomllib

    rig = load_preset("paper-timelapse")
    again = rig_from_dict(tomllib.loads(rig_toml(replace(rig, toml_text=""))))
    assert again.dark == rig.dark and rig.dark.longest_s == 1.008
    plan = make_plan(rig)
    assert Plan.from_dict(plan.to_dict()).dark_extension == plan.dark_extension
    assert plan.dark_extension["max_s_per_direction"] == pytest.approx(0.504 + 1.008 + 2 * rig.camera_a.readout_s)
    data = tomllib.loads(rig.toml_text)
    for key, value, msg in [("longest_s", 0.3, "below twice the bracket's longest exposure"),
                            ("percentile", 100.0, r"must be in \(0, 100\)"), ("snr", -1.0, "positive")]:
        bad = {**data, "dark": {**data["dark"], key: value}}
        with pytest.raises(ConfigurationError, match=rf"\[dark\].*{key}.*{msg}|{key}.*{msg}"):
            rig_from_dict(bad, "rig.toml")
    assert make_plan(replace(rig, dark=None)).dark_extension is None


def dim_renderer(rates_dn_s):
    """A uniform scene per direction (pan decides its brightness, DN/s), with the CMV2000's shot and read noise."""

    def render(camera, pan_deg, tilt_deg, exposure_s, rng):
        rate = rates_dn_s(pan_deg) * (1.0 if camera == "A" else 0.7)
        return CMV2000.sample_dn(np.full(SHAPE, rate * exposure_s * CMV2000.gain_e_per_dn), rng).astype(np.uint16)

    return render


def _rate(pan_deg):
    """Directions on the western half are dim: 400 DN/s, 100 DN in the bracket's longest 0.252 s."""
    return 400.0 if pan_deg < 0 else 40000.0


def _devices(rig, clock, faults=None, rate=_rate):
    head = SimulatedHead(clock, rig.head.pan_speed_deg_s, rig.head.tilt_speed_deg_s, rig.head.settle_s)
    cams = {c: SimulatedCamera(c, head, dim_renderer(rate), clock, 12, rig.cameras[c].readout_s,
                               faults=(faults or {}).get(c, CameraFaults())) for c in ("A", "B")}
    return head, cams


def _session(tmp_path):
    rig = load_preset("small")
    return rig, Session.create(tmp_path / "s", rig, make_plan(rig), kind="test")


def test_dim_directions_get_longer_exposures_that_the_merge_uses(tmp_path):
    rig, s = _session(tmp_path)
    plan = s.plan()
    clock = FakeClock(START)
    res = run_capture(s, *_devices(rig, clock), clock, progress=False)
    ext = dark_extensions(s, plan)
    dim = {d.index for d in plan.directions if d.pan_deg < 0}
    # B at 70 DN in 0.252 s: 532 / 70 = 7.6 wants three doublings, the plan has two (up to 1.008 s)
    assert set(ext) == {d.index for d in plan.directions} and {d for d, n in ext.items() if n} == dim
    assert all(ext[d] == 2 for d in dim)
    assert res.complete and res.n_written == 36 * 2 * 15 + len(dim) * 2 * 2 == res.n_planned
    frame, meta = s.read_frame(min(dim), "B", DARK_EXPOSURE_BASE + 1)
    assert meta["exposure_s"] == pytest.approx(1.008) and frame.shape == SHAPE
    report = verify_session(s.path, check_pixels=True)
    assert report["complete"] and report["n_planned"] == res.n_planned
    # the merge takes them: the dim direction's radiance error falls as 1 / sqrt(exposure) for shot noise
    d = min(dim)
    errors = {}
    for name, indices in (("bracket", bracket_indices(plan, 0)), ("extended", bracket_indices(plan, ext[d]))):
        radiance, _ = merge_direction(s, d, "A", indices, weight="noise")
        errors[name] = float(np.sqrt(np.mean((radiance / 400.0 - 1.0) ** 2)))
    assert errors["extended"] < 0.1 and errors["bracket"] > 1.7 * errors["extended"], errors
    # a lost frame of an extension is missing, by name
    (s.path / "frames" / f"d{d:04d}" / f"A_e{DARK_EXPOSURE_BASE:02d}.tif").unlink()
    missing = verify_session(s.path)["missing"]
    assert [(m["direction"], m["camera"], m["exposure_index"]) for m in missing] == [(d, "A", DARK_EXPOSURE_BASE)]


def test_a_run_stopped_inside_an_extension_finishes_it_on_resume(tmp_path):
    rig, s = _session(tmp_path)
    clock = FakeClock(START)
    # the first direction (pan -165) is dim: 30 regular frames, then the extension; A dies within it
    res = run_capture(s, *_devices(rig, clock, {"A": CameraFaults(dead_after_frames=16)}), clock,
                      RetryPolicy(retries=0), progress=False)
    assert not res.complete and dark_extensions(s, s.plan()) == {0: 2}
    done = set(s.completed())
    assert (0, "A", DARK_EXPOSURE_BASE) in done and (0, "A", DARK_EXPOSURE_BASE + 1) not in done
    res2 = run_capture(s, *_devices(rig, clock), clock, progress=False)
    assert res2.complete and res2.n_already_done == len(done)
    assert {k for k in s.completed() if k[0] == 0 and k[2] >= DARK_EXPOSURE_BASE} == {
        (0, c, DARK_EXPOSURE_BASE + j) for c in "AB" for j in range(2)}
    assert verify_session(s.path)["complete"]
    assert sum(e.get("event") == "dark" and e["direction"] == 0 for e in s.events()) == 1  # metered once


def test_dark_frames_cover_the_extension(tmp_path):
    rig, s = _session(tmp_path)
    record_darks(s, simulated_dark_cameras(rig, seed=1), n_frames=1)
    darks = load_darks(s.path)
    assert {k for c, k in darks if c == "A"} == set(range(15)) | {DARK_EXPOSURE_BASE, DARK_EXPOSURE_BASE + 1}


def test_a_camera_that_clamps_the_exposure_is_recorded_and_merged_with_the_exposure_it_set(tmp_path, capsys):
    """A real camera clamps a request beyond its range (GenTL ``ExposureTime.max``): B here cannot expose longer than
    0.4 s, so the extension's 0.504 s and 1.008 s become 0.4 s.  The journal, the dark frames and the merge must
    use 0.4 s; dividing by the requested times would make B's dim radiance 1.3-2.5x too low there."""
    rig, s = _session(tmp_path)
    plan = s.plan()
    clock = FakeClock(START)
    head, cams = _devices(rig, clock)
    cams["B"].max_exposure_s = 0.4
    res = run_capture(s, head, cams, clock, progress=False)
    assert res.complete
    dim = sorted(d.index for d in plan.directions if d.pan_deg < 0)
    assert res.exposures_set_otherwise == [
        {"camera": "B", "exposure_index": DARK_EXPOSURE_BASE + j, "requested_s": pytest.approx(t), "set_s": 0.4,
         "n_frames": len(dim)} for j, t in enumerate((0.504, 1.008))]
    _print_exposures_set_otherwise(res.exposures_set_otherwise)  # what `capture` prints under its summary
    out = " ".join(capsys.readouterr().out.split())
    assert f"camera B set 0.4 s for the planned 1.008 s (exposure {DARK_EXPOSURE_BASE + 1}, {len(dim)} frames)" in out
    _, meta = s.read_frame(dim[0], "B", DARK_EXPOSURE_BASE + 1)
    assert meta["exposure_s"] == 0.4 and meta["exposure_s_requested"] == pytest.approx(1.008)
    assert s.read_frame(dim[0], "A", DARK_EXPOSURE_BASE + 1)[1]["exposure_s"] == pytest.approx(1.008)
    # B's dim radiance (0.7 x 400 DN/s) from the extended bracket: unbiased with the exposure the camera set
    radiance, _ = merge_direction(s, dim[0], "B", bracket_indices(plan, 2), weight="noise")
    assert abs(float(np.median(radiance)) / 280.0 - 1.0) < 0.02, float(np.median(radiance))
    # dark frames are recorded at the exposure the camera sets; one recorded at another exposure is refused by name
    _, darks_cams = _devices(rig, FakeClock(START), rate=lambda pan_deg: 0.0)  # lenses capped
    darks_cams["B"].max_exposure_s = 0.4
    record_darks(s, darks_cams, n_frames=1)
    index_path = s.path / "darks" / "darks.json"
    index = json.loads(index_path.read_text())
    entry = next(e for e in index["frames"] if e["camera"] == "B" and e["exposure_index"] == DARK_EXPOSURE_BASE + 1)
    assert entry["exposure_s"] == 0.4 and entry["exposure_s_requested"] == pytest.approx(1.008)
    raw = RawSettings.of(s, rig, "B")
    merged, _ = merge_direction(s, dim[0], "B", bracket_indices(plan, 2), raw, weight="noise")
    assert abs(float(np.median(merged)) / 280.0 - 1.0) < 0.02, float(np.median(merged))
    entry["exposure_s"] = 1.008
    index_path.write_text(json.dumps(index))
    with pytest.raises(InputFileError, match=rf"B_e{DARK_EXPOSURE_BASE + 1}\.tif.*recorded at 1\.008 s, but "
                                             rf"frame frames/d{dim[0]:04d}/B_e{DARK_EXPOSURE_BASE + 1}\.tif"):
        merge_direction(s, dim[0], "B", bracket_indices(plan, 2), RawSettings.of(s, rig, "B"), weight="noise")
