"""HDR from files: response recovery, exposure times, the CLI, ghosts, bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from omnispectral.cli import main
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging import merge_exposures
from omnispectral.imaging.bracket import (
    exif_exposure_s,
    exposure_time_mismatches,
    load_bracket,
    merge_bracket,
    parse_exposure_s,
    read_exr,
    read_times_list,
    write_float_image,
)
from omnispectral.imaging.response import CameraResponse, recover_response
from omnispectral.spectral.noise import CMV2000

PAPER_TIMES_S = np.geomspace(252e-3, 0.015e-3, 15)


def _lum(x):
    return x @ np.array([0.2126, 0.7152, 0.0722])


def _write_png(path, img):
    import cv2

    assert cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1]))


def _write_jpeg_with_exif(path, img, exposure_s):
    from PIL import Image
    from PIL.TiffImagePlugin import IFDRational

    exif = Image.Exif()
    exif.get_ifd(0x8769)[0x829A] = IFDRational(*exposure_s.as_integer_ratio())
    Image.fromarray(img).save(path, quality=95, exif=exif)


# ------------------------------------------------------------------ response recovery
def _gamma_bracket(rng, times, h=120, w=160):
    """8-bit frames through a known response X -> 255 * (X / Xmax)^(1/2.2), with mild noise."""
    radiance = np.exp(rng.uniform(np.log(0.05), np.log(400.0), (h, w, 3)))
    frames = []
    for t in times:
        x = np.clip(radiance * t / 8.0, 0, 1)
        z = 255.0 * x ** (1 / 2.2) + rng.normal(0, 0.3, x.shape)
        frames.append(np.clip(np.round(z), 0, 255).astype(np.uint8))
    return radiance, frames


def test_debevec_recovers_a_known_response():
    rng = np.random.default_rng(0)
    times = 2.0 ** -np.arange(0, 12)
    _, frames = _gamma_bracket(rng, times)
    resp = recover_response(frames, times)
    z = np.arange(20, 240)
    truth = (z / 128.0) ** 2.2  # relative to the anchor code 128 (g(128) = 0)
    for c in range(3):
        log_err = np.abs(np.log(resp.linear[z, c] / resp.linear[128, c]) - np.log(truth))
        assert np.median(log_err) < 0.03 and log_err.max() < 0.1, (c, np.median(log_err), log_err.max())
        assert np.all(np.diff(resp.linear[:, c]) >= 0)


def test_merge_with_recovered_response_matches_truth_up_to_scale():
    rng = np.random.default_rng(1)
    times = 2.0 ** -np.arange(0, 12)
    radiance, frames = _gamma_bracket(rng, times)
    result, resp, depth = merge_bracket(_bracket(frames, times), weight="noise")
    assert depth == 8 and resp.kind == "debevec1997"
    ratio = np.log(result.radiance / radiance)[result.valid]
    assert np.std(ratio - np.median(ratio)) < 0.05


def _bracket(frames, times):
    from pathlib import Path

    from omnispectral.imaging.bracket import Bracket

    return Bracket(tuple(Path(f"f{k}.png") for k in range(len(frames))), tuple(frames), np.asarray(times),
                   ("given",) * len(frames))


def test_memorial_bracket_matches_debevecs_radiance_map(shared_data):
    import cv2

    d = shared_data / "hdr_brackets" / "memorial_debevec1997"
    paths = sorted(d.glob("memorial00*.png"))
    bracket = load_bracket(paths, times_list=d / "memorial.hdr_image_list.txt")
    assert bracket.exposure_s[0] == 32 and bracket.exposure_s[-1] == 1 / 1024
    result, response, depth = merge_bracket(bracket, weight="noise")
    assert exposure_time_mismatches(bracket, response, depth) == []  # a dark floor (codes 13-19) does not fool it
    ref = cv2.imread(str(d / "memorial.hdr"), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float64)
    ok = result.valid.all(axis=2)  # the blue border (0, 0, 255) is flagged: zero codes and clipped blue
    assert 0.9 < ok.mean() < 0.97
    ours = np.corrcoef(np.log(_lum(result.radiance)[ok]), np.log(_lum(ref)[ok]))[0, 1]
    # OpenCV's Debevec calibration and merge on the same frames, same pixels
    imgs = [cv2.imread(str(p)) for p in paths]
    t = bracket.exposure_s.astype(np.float32)
    theirs_img = cv2.createMergeDebevec().process(imgs, t, cv2.createCalibrateDebevec().process(imgs, t))[..., ::-1]
    both = ok & (_lum(theirs_img) > 0)
    theirs = np.corrcoef(np.log(_lum(theirs_img)[both]), np.log(_lum(ref)[both]))[0, 1]
    assert ours > 0.99 and ours > theirs


# ------------------------------------------------------------------ exposure times
@pytest.mark.parametrize(("text", "value"), [("1/250", 0.004), ("0.5", 0.5), ("32", 32.0), ("1/1024s", 1 / 1024)])
def test_parse_exposure(text, value):
    assert parse_exposure_s(text) == pytest.approx(value)


@pytest.mark.parametrize("text", ["0", "-1", "abc", "1/0"])
def test_parse_exposure_rejects(text):
    with pytest.raises(ConfigurationError, match="exposure time"):
        parse_exposure_s(text)


def test_times_list_errors_name_the_line(tmp_path):
    p = tmp_path / "list.txt"
    p.write_text("# header\n2\na.png 1/2\nb.png zero\n")
    with pytest.raises(InputFileError, match=r"list.txt, line 4"):
        read_times_list(p)
    p.write_text("2\na.ppm 1/2\nb.ppm 2\n")
    assert read_times_list(p) == {"a": 0.5, "b": 2.0}


def test_exif_times_are_read(tmp_path):
    rng = np.random.default_rng(2)
    times = [1 / 250, 1 / 60, 1 / 15]
    _, frames = _gamma_bracket(rng, times, 32, 48)
    paths = []
    for k, (f, t) in enumerate(zip(frames, times, strict=True)):
        paths.append(tmp_path / f"img{k}.jpg")
        _write_jpeg_with_exif(paths[-1], f, t)
    assert exif_exposure_s(paths[1]) == pytest.approx(1 / 60)
    b = load_bracket(paths)
    np.testing.assert_allclose(b.exposure_s, times)
    assert b.time_sources == ("exif",) * 3
    _write_png(tmp_path / "noexif.png", frames[0])
    with pytest.raises(ConfigurationError, match=r"no exposure time for noexif.png"):
        load_bracket([*paths[:2], tmp_path / "noexif.png"])


# ------------------------------------------------------------------ bad input
def test_truncated_and_unreadable_files_are_named(tmp_path):
    rng = np.random.default_rng(3)
    _, frames = _gamma_bracket(rng, [0.01, 0.1], 64, 64)
    good = tmp_path / "good.jpg"
    _write_jpeg_with_exif(good, frames[0], 0.01)
    data = good.read_bytes()
    bad = tmp_path / "cut.jpg"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputFileError, match=r"cut.jpg: damaged JPEG"):
        load_bracket([good, bad], times=["0.01", "0.1"])
    text = tmp_path / "notes.png"
    text.write_text("not an image")
    with pytest.raises(InputFileError, match=r"notes.png: not a readable image"):
        load_bracket([good, text], times=["0.01", "0.1"])
    with pytest.raises(InputFileError, match=r"missing.png: file not found"):
        load_bracket([good, tmp_path / "missing.png"], times=["0.01", "0.1"])


def test_mismatched_sizes_and_times(tmp_path):
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    _write_png(a, np.zeros((8, 8, 3), np.uint8))
    _write_png(b, np.zeros((8, 9, 3), np.uint8))
    with pytest.raises(InputFileError, match=r"b.png: is \(8, 9, 3\) uint8 but a.png is \(8, 8, 3\)"):
        load_bracket([a, b], times=["1", "2"])
    with pytest.raises(ConfigurationError, match="2 files but 1 exposure times"):
        load_bracket([a, b], times=["1"])
    with pytest.raises(ConfigurationError, match="not positive"):
        load_bracket([a, a], times=["1", "-2"])


# ------------------------------------------------------------------ CLI and files
def _raw_tiffs(tmp_path, rng, times=PAPER_TIMES_S[::2]):
    import tifffile

    truth = np.exp(rng.uniform(np.log(1e2), np.log(1e6), (40, 56, 3))).astype(np.float32)
    paths, frames = [], []
    for k, t in enumerate(times):
        f = CMV2000.sample_dn(truth * t * CMV2000.gain_e_per_dn, rng).astype(np.uint16)
        paths.append(tmp_path / f"raw{k:02d}.tif")
        tifffile.imwrite(paths[-1], f)
        frames.append(f)
    return truth, frames, paths, times


def test_cli_merges_raw_tiffs_to_exr(tmp_path, capsys):
    truth, frames, paths, times = _raw_tiffs(tmp_path, np.random.default_rng(4))
    out = tmp_path / "merged.exr"
    code = main(["hdr", "merge", *map(str, paths), "--bit-depth", "12", "--times", *map(str, times),
                 "-o", str(out), "--with-variance", "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["weight"] == "triangle" and summary["response"] == "linear" and summary["bit_depth"] == 12
    img, names = read_exr(out)
    assert names[:3] == ["R", "G", "B"] and "variance.G" in names and "valid" in names
    expected = merge_exposures(frames, times, 12)
    np.testing.assert_array_equal(img[..., :3], expected.radiance)
    assert np.median(np.abs(img[..., :3] - truth) / truth) < 0.03


def test_cli_reports_bad_input_in_one_line(tmp_path):
    _, _, paths, times = _raw_tiffs(tmp_path, np.random.default_rng(5), PAPER_TIMES_S[:3])
    paths[1].write_bytes(paths[1].read_bytes()[:200])
    r = subprocess.run([sys.executable, "-m", "omnispectral.cli", "hdr", "merge", *map(str, paths), "--times",
                        *map(str, times), "-o", str(tmp_path / "x.exr")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1
    assert "raw01.tif" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "x.exr").exists()


def test_write_and_read_many_channel_exr(tmp_path):
    img = np.random.default_rng(6).random((12, 10, 6), dtype=np.float32)
    names = ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"]
    write_float_image(tmp_path / "six.exr", img, names)
    back, got = read_exr(tmp_path / "six.exr")
    assert sorted(got) == sorted(names)
    np.testing.assert_array_equal(back[..., [got.index(n) for n in names]], img)
    with pytest.raises(ConfigurationError, match=r"Radiance .hdr holds 3 channels"):
        write_float_image(tmp_path / "six.hdr", img)
    assert not (tmp_path / "six.hdr").exists()


def test_response_file_round_trip(tmp_path):
    rng = np.random.default_rng(7)
    _, frames = _gamma_bracket(rng, 2.0 ** -np.arange(8), 48, 64)
    resp = recover_response(frames, 2.0 ** -np.arange(8))
    resp.save(tmp_path / "r.json")
    back = CameraResponse.load(tmp_path / "r.json")
    np.testing.assert_allclose(back.linear, resp.linear, rtol=1e-6)
    (tmp_path / "bad.json").write_text("{\"linear\": [[1, 0.5]]}")
    with pytest.raises(InputFileError, match=r"bad.json: response is not monotonic"):
        CameraResponse.load(tmp_path / "bad.json")


# ------------------------------------------------------------------ ghosts
def _moving_disc_bracket(rng, times, ref):
    h, w = 96, 160
    yy, xx = np.mgrid[:h, :w]
    background = np.exp(rng.uniform(np.log(1e3), np.log(1e5), (h, w, 3))).astype(np.float32)

    def scene(k):
        s = background.copy()
        s[(yy - 48) ** 2 + (xx - 20 - 8 * k) ** 2 < 12**2] = (2e5, 5e4, 1e4)
        return s

    frames = [CMV2000.sample_dn(scene(k) * t * CMV2000.gain_e_per_dn, rng).astype(np.uint16)
              for k, t in enumerate(times)]
    moving = np.any([(scene(k) != background).any(-1) for k in range(len(times))], axis=0)
    return scene(ref), frames, moving


def test_deghosting_takes_a_moving_object_from_the_reference_exposure():
    ref = 7
    truth, frames, moving = _moving_disc_bracket(np.random.default_rng(8), PAPER_TIMES_S, ref)
    plain = merge_exposures(frames, PAPER_TIMES_S, 12, weight="noise")
    clean = merge_exposures(frames, PAPER_TIMES_S, 12, weight="noise", deghost=True, reference=ref)
    err = lambda r: np.abs(r.radiance - truth) / truth  # noqa: E731
    assert err(clean)[moving].mean() < err(plain)[moving].mean() / 4
    assert np.percentile(err(clean)[moving], 95) < 0.15
    # the static background is left alone: few false detections, same accuracy
    assert (clean.ghost & ~moving).mean() < 0.03
    assert np.median(err(clean)[~moving]) == pytest.approx(np.median(err(plain)[~moving]), rel=0.05)


@pytest.mark.parametrize("wrong", ["none", "one", "reversed"])
def test_cli_warns_once_when_exposure_times_disagree_with_the_frames(tmp_path, capsys, wrong):
    """Frame brightness ratios (median over values usable in both) against the stated times: right times say
    nothing; one wrong time names both pairs it belongs to; times in the wrong order name every pair."""
    _, _, paths, times = _raw_tiffs(tmp_path, np.random.default_rng(6), PAPER_TIMES_S[::2][:5])
    stated = list(times)
    if wrong == "one":
        stated[2] = times[2] / 3
    elif wrong == "reversed":
        stated = stated[::-1]
    out = tmp_path / "merged.exr"
    assert main(["hdr", "merge", *map(str, paths), "--bit-depth", "12", "--times", *map(str, stated),
                 "-o", str(out), "--json"]) == 0
    captured = capsys.readouterr()
    warnings = json.loads(captured.out)["exposure_time_warnings"]
    if wrong == "none":
        assert warnings == [] and captured.err == ""
        return
    assert captured.err.count("\n") == 1 and "exposure times inconsistent with the frames" in captured.err
    assert "--times" in captured.err and out.is_file()
    if wrong == "one":  # raw02 is 3x shorter than its real time: its two neighbours disagree with it
        assert len(warnings) == 2 and all("raw02.tif" in w for w in warnings)
        assert "raw01.tif" in captured.err and "raw03.tif" in captured.err
    else:
        assert len(warnings) == 4
