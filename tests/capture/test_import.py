"""``omnispectral import``: sessions from photographs made elsewhere (Papywizard XML, Hugin .pto, CSV; EXIF, table)."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from omnispectral.capture.importer import import_images, list_images, read_directions
from omnispectral.capture.session import Session, verify_session
from omnispectral.cli import main
from omnispectral.errors import InputFileError
from omnispectral.imaging.bracket import exif_exposure_s
from omnispectral.product.merge import merge_direction
from omnispectral.rig import rig_from_dict
from omnispectral.sim.photographs import write_photographs
from omnispectral.sim.simulate import RigRenderer, true_mounting_error_deg
from omnispectral.sim.truth import write_ground_truth
from tests.reliability.test_fault_injection import tiny_rig


@pytest.fixture(scope="module")
def photographed(tmp_path_factory):
    """16-bit TIFF brackets of both cameras of the tiny rig (noise-free) with Papywizard XMLs and exposure tables."""
    from omnispectral.sim.scenes import ProceduralOutdoorScene

    root = tmp_path_factory.mktemp("photos")
    rig, scene = tiny_rig(), ProceduralOutdoorScene(time_hhmm="12:00")
    renderer = RigRenderer(rig, scene, noise=False, b_mounting_error_deg=true_mounting_error_deg(0))
    files = {c: write_photographs(root / c, rig, scene, c, fmt="tiff", noise=False, renderer=renderer) for c in "AB"}
    (root / "rig.toml").write_text(rig.toml_text)
    return root, rig, renderer, files


def test_papywizard_import_rebuilds_the_capture(photographed, tmp_path, capsys):
    root, rig, renderer, files = photographed
    for c in "AB":
        assert main(["import", "--rig", str(root / "rig.toml"), "--camera", c, "--images", str(root / c),
                     "--directions", files[c]["papywizard"], "--exposures", files[c]["exposures"],
                     "-o", str(tmp_path / "s"), "--json"]) == 0
        summary = json.loads(capsys.readouterr().out)
    assert summary["cameras_imported"] == ["A", "B"] and summary["n_images"] == 72
    report = verify_session(tmp_path / "s", check_pixels=True)
    assert report["complete"] and report["n_ok"] == 12 * 2 * 6
    s = Session.open(tmp_path / "s")
    assert s.metadata()["kind"] == "import"
    plan = s.plan()
    assert plan.n_directions == 12 and np.allclose(plan.exposures_s, rig.bracket.exposures_s)
    frame, meta = s.read_frame(7, "B", 3)
    assert meta["camera_metadata"]["response"] == "linear" and meta["camera_metadata"]["exposure_source"] == "table"
    d = plan.directions[7]
    expected = renderer("B", d.pan_deg, d.tilt_deg, plan.exposures_s[3], None)
    assert np.array_equal(frame, expected) and d.pan_deg == rig_plan_pan(rig, 7)
    # the merge of an imported bracket equals the noise-free truth (DN/s) to quantisation
    radiance, _ = merge_direction(s, 7, "A", len(plan.exposures_s), weight="noise")
    truth = renderer.electrons_per_second("A", d.pan_deg, d.tilt_deg) / rig.camera_a.noise_model().gain_e_per_dn
    ok = renderer.pixel_valid("A")[..., None] & (truth * plan.exposures_s[-1] < 3000) & (truth > 50)
    assert np.median(np.abs(radiance[ok] / truth[ok] - 1)) < 0.003


def rig_plan_pan(rig, index):
    from omnispectral.capture.plan import make_plan

    return make_plan(rig).directions[index].pan_deg


def test_import_errors_name_the_file(photographed, tmp_path, capsys):
    root, _, _, files = photographed
    images = list_images(root / "A")
    xml = Path(files["A"]["papywizard"]).read_text()
    bad = tmp_path / "short.xml"
    bad.write_text(xml.replace('<pict id="1"', '<pict id="x"'))
    with pytest.raises(InputFileError, match=r"short.xml: <pict id='x'>: id is not an integer"):
        read_directions(bad, images)
    bad.write_text(xml.replace('roll="0.0"', 'roll="5.0"', 1))
    with pytest.raises(InputFileError, match=r"head roll 5\.0 deg"):
        read_directions(bad, images)
    with pytest.raises(InputFileError, match=r"lists 72 pictures but 71 images"):
        read_directions(Path(files["A"]["papywizard"]), images[:-1])
    csv = tmp_path / "d.csv"
    csv.write_text("file,pan_deg\nA_d0000_e00.tif,0\n")
    with pytest.raises(InputFileError, match="has no column 'tilt_deg'"):
        read_directions(csv)
    # no exposure time anywhere (TIFFs without EXIF, no table): the CLI names the file, one line, exit != 0
    assert main(["import", "--rig", str(root / "rig.toml"), "--images", str(root / "A"), "--directions",
                 files["A"]["papywizard"], "-o", str(tmp_path / "s")]) != 0
    err = capsys.readouterr().err.strip()
    assert "A_d0000_e00.tif" in err and "no exposure time" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "s" / "session.json").exists()


def test_csv_directions_and_a_wrong_image_size(photographed, tmp_path):
    root, rig, _, files = photographed
    entries = read_directions(Path(files["A"]["csv"]), list_images(root / "A"))
    assert len(entries) == 72 and entries[0].path.name == "A_d0000_e00.tif"
    other = rig_from_dict(tomllib.loads(rig.toml_text.replace("width_px = 96", "width_px = 98")), "x",
                          rig.toml_text)
    from omnispectral.capture.importer import read_exposure_table

    with pytest.raises(InputFileError, match=r"A_d0000_e00.tif: image of 96x52 px x 3; camera A of the rig is 98x52"):
        import_images(tmp_path / "s", other, "A", entries, exposure_table=read_exposure_table(files["A"]["exposures"]))


@pytest.mark.slow
def test_jpeg_brackets_with_exif_and_pto_from_an_hdr_panorama_import_and_process(tmp_path, capsys, shared_data):
    """bracketed JPEGs (EXIF exposure times) + Hugin .pto, rendered from a real HDR panorama
    (Poly Haven's venice_sunset, shared data) with the simulator's camera model, import and process; the panorama
    is compared with the scene's truth."""
    from omnispectral.sim.scenes import PanoramaScene

    scene = PanoramaScene(shared_data / "hdr_envmaps" / "polyhaven_1k_hdr" / "venice_sunset_1k.hdr")
    rig = tiny_rig()
    renderer = RigRenderer(rig, scene, b_mounting_error_deg=(0.0, 0.0, 0.0))
    files = {c: write_photographs(tmp_path / c, rig, scene, c, fmt="jpeg", renderer=renderer) for c in "AB"}
    first = Path(files["A"]["images"][0])
    assert first.suffix == ".jpg" and exif_exposure_s(first) == pytest.approx(rig.bracket.exposures_s[0], rel=1e-3)
    (tmp_path / "rig.toml").write_text(rig.toml_text)
    for c in "AB":
        assert main(["import", "--rig", str(tmp_path / "rig.toml"), "--camera", c, "--directions", files[c]["pto"],
                     "-o", str(tmp_path / "s")]) == 0
    write_ground_truth(tmp_path / "s" / "ground_truth", renderer, 256)
    assert main(["process", str(tmp_path / "s"), "-o", str(tmp_path / "p"), "--registration", "paper"]) == 0
    capsys.readouterr()
    report = json.loads((tmp_path / "p" / "report" / "report.json").read_text())
    _, meta = Session.open(tmp_path / "s").read_frame(0, "A", 0)
    assert meta["camera_metadata"]["response"] == "srgb" and meta["camera_metadata"]["exposure_source"] == "exif"
    # 8-bit sRGB JPEGs of a 6-exposure bracket, merged through the sRGB curve: the six bands against the truth
    # (measured 45.7 dB on venice_sunset with the tiny rig; the small rig: 60.1, docs/benchmarks.md)
    assert report["accuracy"]["six_band_psnr_db"] > 45, report["accuracy"]


def write_dng(path: Path, mosaic: np.ndarray, black_level: int, white_level: int) -> None:
    """A minimal uncompressed DNG (TIFF/EP CFA, DNG 1.4 tags) of an RGGB mosaic, as a camera's converter writes."""
    import tifffile

    tags = [(33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True),  # CFARepeatPatternDim, CFAPattern
            (50706, "B", 4, (1, 4, 0, 0), True), (50708, "s", 0, "omnispectral simulated camera", True),
            (50714, "H", 1, (black_level,), True), (50717, "H", 1, (white_level,), True),
            (50721, "2i", 9, (10000, 10000, 0, 10000, 0, 10000) * 3, True), (50778, "H", 1, (21,), True)]
    tifffile.imwrite(path, mosaic, photometric=32803, extratags=tags, subfiletype=0, metadata=None)


def test_camera_raw_dng_import_is_a_bayer_session(tmp_path):
    """DNGs (read by rawpy/LibRaw) keep their mosaic, CFA layout and black level; the merge demosaics them."""
    pytest.importorskip("rawpy", reason="rawpy is not installed (pip install 'omnispectral[raw]')")
    from omnispectral.capture.plan import make_plan
    from omnispectral.rig import rig_with_camera_settings
    from omnispectral.sim.scenes import ProceduralOutdoorScene
    from omnispectral.sim.simulate import bayer_rig

    rig = tiny_rig()
    raw_rig = rig_with_camera_settings(bayer_rig(rig), {"A": {"black_level_dn": 64.0}})
    renderer = RigRenderer(raw_rig, ProceduralOutdoorScene(time_hhmm="12:00"), noise=False)
    plan = make_plan(rig)
    lines = ["file,pan_deg,tilt_deg,exposure_s"]
    for d in plan.directions[:2]:
        for k, t in enumerate(plan.exposures_s):
            mosaic = renderer("A", d.pan_deg, d.tilt_deg, t, None)
            assert mosaic.shape == (52, 96)
            write_dng(tmp_path / f"IMG_{d.index}_{k}.dng", mosaic, 64, 4095)
            lines.append(f"IMG_{d.index}_{k}.dng,{d.pan_deg},{d.tilt_deg},{t!r}")
    (tmp_path / "dirs.csv").write_text("\n".join(lines) + "\n")
    out = import_images(tmp_path / "s", rig, "A", read_directions(tmp_path / "dirs.csv"))
    assert out["n_directions"] == 2 and out["n_exposures"] == 6
    s = Session.open(tmp_path / "s")
    frame, meta = s.read_frame(1, "A", 2)
    cm = meta["camera_metadata"]
    assert frame.shape == (52, 96) and cm["cfa_pattern"] == "RGGB" and cm["black_level"] == 64.0
    assert cm["white_level"] == 4095 and cm["response"] == "linear"
    # the session's rig is the plain RGB one: the frames' own metadata make the merge subtract and demosaic
    d = plan.directions[1]
    radiance, _ = merge_direction(s, 1, "A", 6, weight="noise")
    assert radiance.shape == (52, 96, 3)
    truth = renderer.electrons_per_second("A", d.pan_deg, d.tilt_deg) / rig.camera_a.noise_model().gain_e_per_dn
    ok = renderer.pixel_valid("A")[..., None] & (truth * plan.exposures_s[-1] < 3000) & (truth > 50)
    ok[:3], ok[-3:], ok[:, :3], ok[:, -3:] = False, False, False, False
    ratio = radiance[ok] / truth[ok]
    assert abs(np.median(ratio) - 1) < 0.01 and np.median(np.abs(ratio - 1)) < 0.05


def test_referenced_one_camera_import_is_verified_and_processed_in_place(tmp_path, capsys):
    """``import --reference`` of one RGB camera: nothing copied, the journal holds each file's absolute path,
    size, mtime and SHA-256; process reads the files in place (accuracy against the truth); a changed or moved
    file is named on one line by ``session verify`` and refused by ``process``."""
    import os

    import tifffile

    from omnispectral.capture.resume import repair_session
    from tests.product.test_three_bands import chart_scene, rgb_rig

    rig, scene = rgb_rig(), chart_scene()
    renderer = RigRenderer(rig, scene)
    files = write_photographs(tmp_path / "photos", rig, scene, "A", fmt="tiff", renderer=renderer)
    (tmp_path / "rgb.toml").write_text(rig.toml_text)
    assert main(["import", "--rig", str(tmp_path / "rgb.toml"), "--reference", "--images", str(tmp_path / "photos"),
                 "--directions", files["papywizard"], "--exposures", files["exposures"], "-o", str(tmp_path / "s"),
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["referenced"] and summary["cameras_imported"] == ["A"] and summary["n_images"] == 72
    assert not list((tmp_path / "s" / "frames").rglob("*.tif"))  # nothing copied
    s = Session.open(tmp_path / "s")
    rec = s.completed()[(5, "A", 2)]
    original = tmp_path / "photos" / "A_d0005_e02.tif"
    assert rec["referenced"] and rec["file"] == str(original.resolve()) and Path(rec["file"]).is_absolute()
    assert rec["bytes"] == original.stat().st_size and rec["mtime_ns"] == original.stat().st_mtime_ns
    frame, meta = s.read_frame(5, "A", 2)
    assert np.array_equal(frame, tifffile.imread(original)) and meta["camera_metadata"]["response"] == "linear"
    assert verify_session(tmp_path / "s", check_pixels=True)["complete"]
    assert repair_session(tmp_path / "s")["n_dropped"] == 0  # a repair keeps the referenced records
    # process reads them where they are: a three-band product against the truth of the same renderer
    write_ground_truth(tmp_path / "s" / "ground_truth", renderer, 128)
    assert main(["process", str(tmp_path / "s"), "-o", str(tmp_path / "p"), "--json"]) == 0
    index = json.loads(capsys.readouterr().out)
    acc = json.loads((tmp_path / "p" / "report" / "report.json").read_text())["accuracy"]
    assert index["bands"] == ["A:R", "A:G", "A:B"] and acc["band_psnr_db"] > 33
    assert 1.0 < acc["colorchecker"]["delta_e_ab"] < 10.0  # an RGB camera (measured 5.82, 36.1 dB)
    # one file changed in place (same size), one moved away: each named on its own line
    changed, moved = tmp_path / "photos" / "A_d0003_e01.tif", tmp_path / "photos" / "A_d0007_e04.tif"
    data = tifffile.imread(changed)
    data[10, 10] = (data[10, 10] + 1) % 4096
    tifffile.imwrite(changed, data, photometric="rgb", metadata=None)
    os.rename(moved, tmp_path / "elsewhere.tif")
    assert main(["session", "verify", str(tmp_path / "s")]) == 1
    lines = capsys.readouterr().out.splitlines()
    named = {ln.strip().split(": ", 1)[0]: ln.strip().split(": ", 1)[1] for ln in lines[1:]}
    assert set(named) == {str(changed.resolve()), str(moved.resolve())}, lines
    assert "changed since the import" in named[str(changed.resolve())]
    assert "moved or deleted" in named[str(moved.resolve())]
    assert main(["process", str(tmp_path / "s"), "-o", str(tmp_path / "p2")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and ("A_d0003_e01.tif" in err or "A_d0007_e04.tif" in err), err
    # the moved file back, the changed one with its recorded modification time: only its SHA-256 tells, and the
    # read that would merge it checks that
    os.rename(tmp_path / "elsewhere.tif", moved)
    record = s.completed()[(3, "A", 1)]
    os.utime(changed, ns=(record["mtime_ns"], record["mtime_ns"]))
    assert main(["process", str(tmp_path / "s"), "-o", str(tmp_path / "p3")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "A_d0003_e01.tif" in err and "checksum" in err, err
    assert not (tmp_path / "p3" / "merged").exists()


def _nona_equirect(pto: Path, width: int) -> np.ndarray:
    """Hugin's own remapping (``nona``) of a project's image onto a ``width``-px equirectangular panorama: RGBA."""
    import subprocess

    import tifffile

    text = pto.read_text()
    lines = [f'p f2 w{width} h{width // 2} v360 E0 R0 n"TIFF_m c:NONE"' if ln.startswith("p ") else ln
             for ln in text.splitlines()]
    pto.write_text("\n".join(lines) + "\n")
    subprocess.run(["nona", "-o", str(pto.with_suffix("")) + "_", "-m", "TIFF_m", str(pto)], check=True,
                   cwd=pto.parent, capture_output=True, timeout=60)
    return tifffile.imread(str(pto.with_suffix("")) + "_0000.tif")


@pytest.mark.skipif(not __import__("shutil").which("nona"), reason="Hugin's nona (Debian hugin-tools) not installed")
def test_pto_yaw_pitch_roll_follow_hugin(tmp_path):
    """Hugin's convention, measured with Hugin itself: a portrait (rolled) camera's image at pan 40, tilt 20,
    written to a ``.pto`` as ``y40 p20 r90`` and remapped by ``nona``, lands exactly where our camera model puts
    it; with ``r-90`` Hugin puts it elsewhere.  So ``r`` is the rig's mounting roll with the same sign, and the
    import accepts ``r90`` and refuses ``r-90`` for a portrait rig (a reader with the wrong sign would not)."""
    import math

    import cv2
    import tifffile

    from omnispectral.imaging.geometry import equirect_pixel_to_lonlat, lonlat_to_ray
    from omnispectral.rig import rig_with_camera_settings
    from omnispectral.sim.photographs import write_pto
    from omnispectral.sim.scenes import PanoramaScene

    # square pixels and no distortion: the lens model Hugin's "f0 v60 a0 b0 c0" describes exactly
    w_px, h_px, hfov = 120, 80, 60.0
    vfov = math.degrees(2 * math.atan(h_px / w_px * math.tan(math.radians(hfov / 2))))
    text = tiny_rig().toml_text
    for old, new in (("width_px = 96", f"width_px = {w_px}"), ("height_px = 52", f"height_px = {h_px}"),
                     ("hfov_deg = 120.0", f"hfov_deg = {hfov}"), ("vfov_deg = 61.0", f"vfov_deg = {vfov!r}"),
                     ("distortion = [-0.28, 0.09, 0.0, 0.0, -0.012]", "distortion = []")):
        text = text.replace(old, new)
    rig = rig_with_camera_settings(rig_from_dict(tomllib.loads(text), "hugin", text), {"A": {"filter": "none"}})
    assert rig.camera_a.orientation == "portrait" and rig.camera_a.roll_deg == 90.0
    rng = np.random.default_rng(1)
    base = cv2.GaussianBlur(rng.random((180, 360, 3)).astype(np.float32), (0, 0), 3)
    base = (base - base.min()) / (base.max() - base.min()) + 0.05  # a random texture of full contrast
    renderer = RigRenderer(rig, PanoramaScene(base, scale=1000.0), noise=False)
    pan, tilt = 40.0, 20.0
    img = renderer.electrons_per_second("A", pan, tilt)
    tifffile.imwrite(tmp_path / "img.tif", np.rint(img / img.max() * 4000).astype(np.uint16), photometric="rgb")
    # our model's view of the same image on the same equirectangular grid (the mosaic's inverse map)
    width = 360
    cols, rows = np.meshgrid(np.arange(width), np.arange(width // 2))
    rays = lonlat_to_ray(*equirect_pixel_to_lonlat(cols, rows, width, width // 2))
    px, ok = rig.camera_model("A").world_to_pixel(rays, pan, tilt)
    ours = cv2.remap(tifffile.imread(tmp_path / "img.tif").astype(np.float32), px[..., 0].astype(np.float32),
                     px[..., 1].astype(np.float32), cv2.INTER_LINEAR)
    inside = ok & (px[..., 0] > 1) & (px[..., 0] < w_px - 2) & (px[..., 1] > 1) & (px[..., 1] < h_px - 2)
    disagreement = {}
    for roll in (90.0, -90.0):
        pto = tmp_path / f"r{roll:+.0f}.pto"
        write_pto(pto, [("img.tif", pan, tilt, 1.0)], rig.camera_a)  # Eev 0: nona keeps the values
        pto.write_text(pto.read_text().replace(" r90.000000 ", f" r{roll:.6f} "))
        hugin = _nona_equirect(pto, width)
        both = inside & (hugin[..., 3] > 0)
        assert both.sum() > 0.8 * inside.sum()
        theirs = hugin[..., :3][both].astype(np.float64)
        disagreement[roll] = (float(np.median(np.abs(theirs - ours[both]) / ours[both].mean())),
                              float(np.mean([np.corrcoef(theirs[:, c], ours[both][:, c])[0, 1] for c in range(3)])))
        entries = read_directions(pto)
        assert (entries[0].pan_deg, entries[0].tilt_deg, entries[0].roll_deg) == (pan, tilt, roll)
    # (median relative difference, correlation): r90 the same pixels up to interpolation, r-90 another part of
    # the scene (measured 0.04 %, 0.99999 and 11 %, -0.13; correlation per channel, mean of the three)
    assert disagreement[90.0][0] < 0.005 and disagreement[90.0][1] > 0.999, disagreement
    assert disagreement[-90.0][1] < 0.5, disagreement
    out = import_images(tmp_path / "s", rig, "A", read_directions(tmp_path / "r+90.pto"),
                        exposure_table={"img": 0.01})
    assert out["n_images"] == 1
    with pytest.raises(InputFileError, match=r"roll -90.0 deg .* is not camera A's mounting roll 90.0 deg"):
        import_images(tmp_path / "s2", rig, "A", read_directions(tmp_path / "r-90.pto"), exposure_table={"img": 0.01})
