"""Geometry: equirectangular conventions, head rotation, mounting, OpenCV camera model (project/unproject)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.geometry import (
    CameraModel,
    Mounting,
    equirect_pixel_to_lonlat,
    head_rotation,
    lonlat_to_equirect_pixel,
    lonlat_to_ray,
    monotonic_radius,
    ray_to_lonlat,
)

#: Real calibration of OpenCV's left*.jpg sample boards (cv2.calibrateCamera, 640 x 480).
REAL = dict(width=640, height=480, fx=536.0735, fy=536.0164, cx=342.3705, cy=235.5369,
            dist=(-0.26509, -0.046742, 0.0018330, -0.00031469, 0.25231))

#: Rational (8-coefficient) fit of the same boards (OpenCV's 11 px corner window).  Numerator and denominator
#: nearly cancel (complex root pairs at r² ≈ 0.0829 ± 0.0003i), leaving a ripple: r·g(r²) falls between
#: r ≈ 0.2877 and 0.2885 (θ ≈ 16°), well inside the image, so the model folds there.
REAL_RATIONAL = dict(width=640, height=480, fx=535.8145698337988, fy=535.6366653541695, cx=342.8601275407204,
                     cy=235.72037805622625,
                     dist=(-24.19731636528174, 147.13633111770045, 0.0018304670630908547, -0.0003647507146426214,
                           -9.139872711315245, -23.92326706842105, 140.5180131746347, 30.81873381926129))

#: Distortion strengths for the round trips: each keeps the whole image inside the monotonic region.
CAMERAS = {
    "pinhole": CameraModel(640, 480, 500.0, 500.0, 319.5, 239.5),
    "real-calibration": CameraModel(**REAL),
    "strong-barrel": CameraModel(1024, 768, 560.0, 560.0, 515.2, 380.9, (-0.32, 0.11, 0.0, 0.0, -0.012)),
    "pincushion": CameraModel(800, 600, 900.0, 905.0, 402.0, 297.0, (0.25, 0.08, -0.001, 0.002)),
    "wide-rational": CameraModel(2048, 1088, 940.0, 940.0, 1030.0, 540.0,
                                 (2.1, 0.9, 0.0005, -0.0007, 0.01, 2.5, 1.4, 0.08)),
    "thin-prism-tilted": CameraModel(1280, 960, 1100.0, 1098.0, 641.0, 478.0,
                                     (-0.21, 0.05, 0.0012, -0.0009, 0.01, 0.02, -0.003, 0.001,
                                      0.002, -0.001, 0.0015, 0.0004, 0.004, -0.003)),
}


def _all_pixels(cam: CameraModel) -> np.ndarray:
    """Every pixel centre plus the outer image border (±0.5 px)."""
    u = np.concatenate(([-0.5], np.arange(cam.width, dtype=float), [cam.width - 0.5]))
    v = np.concatenate(([-0.5], np.arange(cam.height, dtype=float), [cam.height - 0.5]))
    uu, vv = np.meshgrid(u, v)
    return np.stack((uu, vv), axis=-1)


# ------------------------------------------------------------------------------------------ equirect
def test_equirect_pixel_centres():
    w, h = 360, 180
    lon, lat = equirect_pixel_to_lonlat(np.array([0, w - 1, w // 2]), np.array([0, h - 1, h // 2]), w, h)
    np.testing.assert_allclose(lon, [-179.5, 179.5, 0.5])
    np.testing.assert_allclose(lat, [89.5, -89.5, -0.5])
    # The centre of the image (between the middle pixels) is lon 0, lat 0 = +Z.
    lon, lat = equirect_pixel_to_lonlat(w / 2 - 0.5, h / 2 - 0.5, w, h)
    assert lon == pytest.approx(0.0) and lat == pytest.approx(0.0)
    np.testing.assert_allclose(lonlat_to_ray(lon, lat), [0.0, 0.0, 1.0], atol=1e-15)


def test_equirect_round_trip_and_seam():
    w, h = 1000, 500
    rng = np.random.default_rng(1)
    col, row = rng.uniform(-0.5, w - 0.5, 10_000), rng.uniform(-0.5, h - 0.5, 10_000)
    lon, lat = equirect_pixel_to_lonlat(col, row, w, h)
    assert lon.min() >= -180.0 and lon.max() < 180.0
    c2, r2 = lonlat_to_equirect_pixel(lon, lat, w, h)
    np.testing.assert_allclose(c2, col, atol=1e-9)
    np.testing.assert_allclose(r2, row, atol=1e-9)
    # ±180° is one meridian: the left border; longitudes wrap.
    c, _ = lonlat_to_equirect_pixel(np.array([180.0, -180.0, 540.0, -190.0]), 0.0, w, h)
    np.testing.assert_allclose(c, [-0.5, -0.5, -0.5, (170.0 + 180.0) / 360.0 * w - 0.5])
    lon, _ = equirect_pixel_to_lonlat(w - 0.5, 0, w, h)  # right border = 180 = -180
    assert lon == pytest.approx(-180.0)
    np.testing.assert_allclose(lonlat_to_ray(180.0, 0.0), lonlat_to_ray(-180.0, 0.0), atol=1e-15)


def test_poles():
    np.testing.assert_allclose(lonlat_to_ray([0.0, 123.0], [90.0, 90.0]), [[0, 1, 0], [0, 1, 0]], atol=1e-15)
    np.testing.assert_allclose(lonlat_to_ray(-45.0, -90.0), [0, -1, 0], atol=1e-15)
    lon, lat = ray_to_lonlat(np.array([[0.0, 2.0, 0.0], [0.0, -1.0, 0.0]]))
    np.testing.assert_allclose(lat, [90.0, -90.0])
    np.testing.assert_allclose(lon, [0.0, 0.0])
    _, row = lonlat_to_equirect_pixel(0.0, [90.0, -90.0], 360, 180)
    np.testing.assert_allclose(row, [-0.5, 179.5])  # top and bottom borders


def test_world_axes_match_mitsuba_envmap():
    """Mitsuba's envmap: u = atan2(x, -z) / 2π (mod 1), v = acos(y) / π; u = 0.25 faces +X, 0.5 faces +Z."""
    rng = np.random.default_rng(2)
    rays = rng.normal(size=(5000, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    u_mitsuba = np.mod(np.arctan2(rays[:, 0], -rays[:, 2]) / (2 * np.pi), 1.0)
    v_mitsuba = np.arccos(rays[:, 1]) / np.pi
    w, h = 4096, 2048
    col, row = lonlat_to_equirect_pixel(*ray_to_lonlat(rays), w, h)
    np.testing.assert_allclose((col + 0.5) / w, u_mitsuba, atol=1e-12)
    np.testing.assert_allclose((row + 0.5) / h, v_mitsuba, atol=1e-12)
    for ray, lon in (((1, 0, 0), -90.0), ((0, 0, 1), 0.0), ((-1, 0, 0), 90.0)):
        got_lon, got_lat = ray_to_lonlat(np.array(ray, float))
        assert got_lon == pytest.approx(lon) and got_lat == pytest.approx(0.0)
    col, _ = lonlat_to_equirect_pixel(*ray_to_lonlat(np.array([1.0, 0, 0])), w, h)
    assert (col + 0.5) / w == pytest.approx(0.25)
    # Right-handed with +Y up: turning right (clockwise from above) from +Z reaches -X at lon +90.
    # (Clockwise seen from +Y is a right-handed rotation by a negative angle about +Y.)
    clockwise_90, _ = cv2.Rodrigues(np.array([0.0, -np.pi / 2, 0.0]))
    np.testing.assert_allclose(lonlat_to_ray(90.0, 0.0), clockwise_90 @ [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(lonlat_to_ray(90.0, 0.0), [-1, 0, 0], atol=1e-15)


def test_lonlat_ray_round_trip_shapes():
    lon, lat = np.meshgrid(np.linspace(-179.9, 179.9, 37), np.linspace(-89.9, 89.9, 19))
    rays = lonlat_to_ray(lon, lat)
    assert rays.shape == (19, 37, 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0)
    lon2, lat2 = ray_to_lonlat(rays * 3.0)
    np.testing.assert_allclose(lon2, lon, atol=1e-10)
    np.testing.assert_allclose(lat2, lat, atol=1e-10)


# ------------------------------------------------------------------------------------------ head and mounting
def _look(r: np.ndarray) -> tuple[float, float]:
    lon, lat = ray_to_lonlat(r @ np.array([0.0, 0.0, 1.0]))
    return float(lon), float(lat)


def test_head_rotation_directions():
    for pan, tilt in ((0, 0), (90, 0), (-90, 0), (30, 20), (-150, -45), (179, 60)):
        r = head_rotation(pan, tilt)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
        assert np.linalg.det(r) == pytest.approx(1.0)
        lon, lat = _look(r)
        assert lon == pytest.approx(pan) and lat == pytest.approx(tilt)
    np.testing.assert_allclose(head_rotation(90, 0) @ [0, 0, 1], lonlat_to_ray(90.0, 0.0), atol=1e-15)
    np.testing.assert_allclose(head_rotation(0, 90) @ [0, 0, 1], [0, 1, 0], atol=1e-15)
    r0 = head_rotation(0, 0)
    np.testing.assert_allclose(r0 @ [0, -1, 0], [0, 1, 0])  # image up is +Y
    assert ray_to_lonlat(r0 @ [1.0, 0, 0]) == pytest.approx((90.0, 0.0))  # image right = turning right
    # Tilt turns with the pan: pan 90 then tilt up keeps longitude 90.
    lon, lat = _look(head_rotation(90, 40))
    assert (lon, lat) == pytest.approx((90.0, 40.0))


def test_camera_pixels_move_with_pan_and_tilt():
    cam = CameraModel.from_fov(640, 480, 60.0)
    rays, _ = cam.pixel_to_world(np.array([[639.5, 239.5], [319.5, -0.5]]), 0.0, 0.0)
    lon, lat = ray_to_lonlat(rays)
    assert lon[0] == pytest.approx(30.0) and lat[0] == pytest.approx(0.0, abs=1e-12)  # right edge: lon +30
    assert lat[1] > 0  # top row looks up
    uv, ok = cam.world_to_pixel(lonlat_to_ray(25.0, 10.0), pan_deg=25.0, tilt_deg=10.0)
    assert ok and uv == pytest.approx([319.5, 239.5])


def test_mounting_roll_misalignment_baseline():
    portrait = CameraModel.from_fov(640, 480, 60.0, mounting=Mounting(roll_deg=90.0))
    # Camera body turned 90° clockwise (seen from behind): the image top points right in the world.
    ray, _ = portrait.pixel_to_world(np.array([portrait.cx, 0.0]), 0.0, 0.0)
    lon, lat = ray_to_lonlat(ray)
    assert lon > 20 and lat == pytest.approx(0.0, abs=1e-9)
    ray, _ = portrait.pixel_to_world(np.array([0.0, portrait.cy]), 0.0, 0.0)  # image left points up
    assert ray_to_lonlat(ray)[1] > 20
    for mis, expected in (((5.0, 0.0, 0.0), (5.0, 0.0)), ((0.0, 3.0, 0.0), (0.0, 3.0)),
                          ((0.0, 0.0, 7.0), (0.0, 0.0))):
        cam = CameraModel.from_fov(640, 480, 60.0, mounting=Mounting(misalignment_deg=mis))
        assert _look(cam.camera_to_world(0.0, 0.0)) == pytest.approx(expected)
    rolled = CameraModel.from_fov(640, 480, 60.0, mounting=Mounting(misalignment_deg=(0, 0, 7.0)))
    r = rolled.camera_to_world(0, 0) @ [1.0, 0, 0]
    assert math.degrees(math.atan2(-r[1], -r[0])) == pytest.approx(7.0)  # x axis turned 7° down (clockwise)
    # Baseline: camera B 100 mm to the right of A sees a near point left of centre, a far one centred.
    a = CameraModel.from_fov(640, 480, 60.0)
    b = CameraModel.from_fov(640, 480, 60.0, mounting=Mounting(baseline_mm=(100.0, 0.0, 0.0)))
    for pan, tilt in ((0.0, 0.0), (70.0, -20.0)):
        near = 1000.0 * lonlat_to_ray(pan, tilt)
        far = 1e9 * lonlat_to_ray(pan, tilt)
        ua, _ = a.world_points_to_pixel(near, pan, tilt)
        ub, _ = b.world_points_to_pixel(near, pan, tilt)
        assert ua == pytest.approx([319.5, 239.5])
        assert ub[0] == pytest.approx(319.5 - a.fx * 100.0 / 1000.0) and ub[1] == pytest.approx(239.5)
        uf, _ = b.world_points_to_pixel(far, pan, tilt)
        np.testing.assert_allclose(uf, b.world_to_pixel(lonlat_to_ray(pan, tilt), pan, tilt)[0], atol=1e-4)
        np.testing.assert_allclose(b.camera_center_mm(pan, tilt), head_rotation(pan, tilt) @ [100.0, 0, 0])


def test_world_round_trip_with_rig():
    cam = CameraModel(**{**REAL, "mounting": Mounting(roll_deg=90.0, misalignment_deg=(0.4, -0.3, 0.2),
                                                     baseline_mm=(0.0, -60.0, 5.0))})
    px = _all_pixels(cam)[::7, ::7]
    for pan, tilt in ((0, 0), (123.0, 35.0), (-170.0, -60.0)):
        rays, ok = cam.pixel_to_world(px, pan, tilt)
        assert ok.all()
        uv, ok = cam.world_to_pixel(rays, pan, tilt, margin_px=1e-6)
        assert ok.all()
        assert np.abs(uv - px).max() < 1e-6


def test_mosaic_style_inverse_map():
    """Equirect pixel → ray → camera pixel → ray → equirect pixel returns where it started."""
    cam = CameraModel(**REAL)
    w, h = 720, 360
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    rays = lonlat_to_ray(*equirect_pixel_to_lonlat(cols, rows, w, h))
    uv, ok = cam.world_to_pixel(rays, 40.0, 15.0)
    assert 0.02 < ok.mean() < 0.2
    assert np.isnan(uv[~ok]).all() and np.isfinite(uv[ok]).all()
    back, ok2 = cam.pixel_to_world(uv[ok], 40.0, 15.0)
    assert ok2.all()
    c2, r2 = lonlat_to_equirect_pixel(*ray_to_lonlat(back), w, h)
    assert np.abs(c2 - cols[ok]).max() < 1e-6 and np.abs(r2 - rows[ok]).max() < 1e-6


# ------------------------------------------------------------------------------------------ camera model
@pytest.mark.parametrize("name", list(CAMERAS))
def test_round_trip_whole_image(name):
    cam = CAMERAS[name]
    px = _all_pixels(cam)
    rays, ok = cam.unproject(px)
    assert ok.all(), f"{(~ok).sum()} pixels not invertible"
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0)
    uv, ok = cam.project(rays, margin_px=1e-6)
    assert ok.all()
    err = np.abs(uv - px).max()
    assert err <= 1e-3, err
    assert err <= 1e-6  # Newton to 1e-12 in normalised coordinates: far better than the 1e-3 px required


@pytest.mark.parametrize("name", [n for n in CAMERAS if n != "pinhole"])
def test_project_matches_cv2_project_points(name):
    cam = CAMERAS[name]
    rng = np.random.default_rng(3)
    rays, _ = cam.unproject(np.stack((rng.uniform(-0.5, cam.width - 0.5, 4000),
                                      rng.uniform(-0.5, cam.height - 0.5, 4000)), axis=-1))
    points = rays * rng.uniform(0.5, 50.0, (4000, 1))
    rvec, tvec = np.zeros(3), np.zeros(3)
    k, dist, _ = cam.to_opencv()
    ref, _ = cv2.projectPoints(points, rvec, tvec, k, dist)
    mine, ok = cam.project(points, margin_px=None)
    assert ok.all()
    assert np.abs(mine - ref.reshape(-1, 2)).max() <= 1e-6
    # And with a board pose, through our own rotation: the same numbers.
    rvec, tvec = np.array([0.1, -0.2, 0.05]), np.array([10.0, -5.0, 100.0])
    rot, _ = cv2.Rodrigues(rvec)
    obj = rng.uniform(-30, 30, (500, 3))
    ref, _ = cv2.projectPoints(obj, rvec, tvec, k, dist)
    mine, _ = cam.project(obj @ rot.T + tvec, margin_px=None)
    assert np.abs(mine - ref.reshape(-1, 2)).max() <= 1e-6


def test_unproject_matches_cv2_undistort_points():
    cam = CAMERAS["real-calibration"]
    px = _all_pixels(cam)[::5, ::5].reshape(-1, 2)
    k, dist, _ = cam.to_opencv()
    ref = cv2.undistortPoints(px.reshape(-1, 1, 2), k, dist,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)).reshape(-1, 2)
    rays, ok = cam.unproject(px)
    assert ok.all()
    np.testing.assert_allclose(rays[:, :2] / rays[:, 2:], ref, atol=1e-8)


def test_fold_back_guard():
    """k1 = -0.5 alone: r(1 - 0.5 r²) peaks at r = 0.816; beyond, rays would fold back into the image."""
    cam = CameraModel(1000, 800, 600.0, 600.0, 499.5, 399.5, (-0.5, 0.0, 0.0, 0.0))
    assert cam.max_radius == pytest.approx(math.sqrt(2.0 / 3.0), rel=5e-3)
    assert cam.max_radius < math.sqrt(2.0 / 3.0)
    far = np.array([1.2, 0.0, 1.0])  # 50° off axis: outside the lens's monotonic region
    naive_u = 600.0 * 1.2 * (1 - 0.5 * 1.2**2) + 499.5
    assert 0 < naive_u < 1000  # the raw model would put it inside the image ...
    uv, ok = cam.project(far)
    assert not ok and np.isnan(uv).all()  # ... the guard rejects it
    near = np.array([0.5, 0.0, 1.0])
    assert cam.project(near)[1]
    # Pixels beyond the largest distorted radius have no ray: invalid, not a wrong ray.
    rays, ok = cam.unproject(np.array([[499.5 + 600.0 * 0.6, 399.5], [499.5 + 600.0 * 0.5, 399.5]]))
    assert ok.tolist() == [False, True] and np.isnan(rays[0]).all()
    # The rational fit of OpenCV's sample boards folds in a narrow ring inside the image: found exactly,
    # although a 3000-step radius grid would step over it.
    rational = CameraModel(**REAL_RATIONAL)
    assert 0.285 < rational.max_radius < 0.2878
    radial = np.polynomial.Polynomial([0, 1, 0, REAL_RATIONAL["dist"][0], 0, REAL_RATIONAL["dist"][1], 0,
                                       REAL_RATIONAL["dist"][4]])
    den = np.polynomial.Polynomial([1, 0, REAL_RATIONAL["dist"][5], 0, REAL_RATIONAL["dist"][6], 0,
                                    REAL_RATIONAL["dist"][7]])
    assert radial(0.2878) / den(0.2878) > radial(0.2884) / den(0.2884)  # the distorted radius really decreases
    rays, ok = rational.unproject(_all_pixels(rational))
    assert 0.2 < ok.mean() < 0.5  # only the centre of the image is invertible
    # Rounded to 5 digits, the same model gets a real pole: also cut before it.
    rounded = CameraModel(640, 480, 535.8, 535.6, 342.9, 235.7,
                          (-24.197, 147.136, 0.00183, -0.000365, -9.1399, -23.923, 140.518, 30.819))
    assert rounded.max_radius < 0.29
    # A lens without folding keeps the whole hemisphere in front.
    assert monotonic_radius(()) == monotonic_radius(REAL["dist"]) == 1e3


def test_validity_behind_and_outside():
    cam = CAMERAS["real-calibration"]
    pts = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [2.0, 0.0, 1.0], [0.62, 0.0, 1.0]])
    uv, ok = cam.project(pts)
    assert ok.tolist() == [False, False, True, False, False]
    _, ok_margin = cam.project(pts, margin_px=None)
    assert ok_margin.tolist() == [False, False, True, True, True]
    assert cam.inside(np.array([-0.5, -0.51, 639.5, 639.51]), 0.0).tolist() == [True, False, True, False]
    # Vectorised over any leading shape.
    uv, ok = cam.project(np.broadcast_to([0.0, 0.0, 1.0], (4, 5, 3)))
    assert uv.shape == (4, 5, 2) and ok.shape == (4, 5) and ok.all()


def test_from_fov():
    cam = CameraModel.from_fov(2048, 1088, 95.0)
    assert cam.fx == cam.fy == pytest.approx(1024.0 / math.tan(math.radians(47.5)))
    assert (cam.cx, cam.cy) == (1023.5, 543.5)
    assert cam.hfov_deg == pytest.approx(95.0)
    assert cam.vfov_deg == pytest.approx(2 * math.degrees(math.atan(544.0 / cam.fy)))
    barrel = CameraModel.from_fov(2048, 1088, 95.0, dist=(-0.2, 0.03, 0.0, 0.0, 0.0))
    assert barrel.hfov_deg == pytest.approx(95.0, abs=1e-6)
    assert barrel.fx > cam.fx  # barrel distortion squeezes the periphery: the same field at a longer f
    with pytest.raises(ConfigurationError):
        CameraModel.from_fov(640, 480, 190.0)


def test_json_round_trip_and_errors(tmp_path):
    cam = CameraModel(**{**REAL, "dist": CAMERAS["thin-prism-tilted"].dist,
                         "mounting": Mounting(roll_deg=90.0, misalignment_deg=(0.1, 0.2, 0.3),
                                              baseline_mm=(0.0, -62.0, 0.0))})
    path = cam.to_json(tmp_path / "cam.json", extra={"note": "kept"})
    data = json.loads(path.read_text())
    assert data["distortion"]["tau_y"] == cam.dist[13] and data["note"] == "kept"
    assert data["image_size"] == {"width": 640, "height": 480}
    assert CameraModel.from_json(path) == cam
    five = CameraModel(**REAL)
    assert CameraModel.from_json(five.to_json(tmp_path / "five.json")) == five
    # Partial names are filled to OpenCV's next vector length.
    d = {**five.to_dict(), "distortion": {"k1": -0.1, "k4": 0.01}}
    assert CameraModel.from_dict(d).dist == (-0.1, 0, 0, 0, 0, 0.01, 0, 0)
    k, dist, size = cam.to_opencv()
    assert CameraModel.from_opencv(k, dist, size, mounting=cam.mounting) == cam

    with pytest.raises(InputFileError, match=r"missing\.json: file not found"):
        CameraModel.from_json(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{\n  'fx': 1\n}")
    with pytest.raises(InputFileError, match=r"bad.json, line 2: not valid JSON"):
        CameraModel.from_json(bad)
    bad.write_text(json.dumps({"fx": 500}))
    with pytest.raises(InputFileError, match=r"bad.json: not a camera model: missing 'image_size'"):
        CameraModel.from_json(bad)
    bad.write_text(json.dumps({**five.to_dict(), "distortion": {"k9": 1.0}}))
    with pytest.raises(InputFileError, match=r"bad.json: .*unknown distortion coefficient"):
        CameraModel.from_json(bad)
    bad.write_text(json.dumps({**five.to_dict(), "fx": -3}))
    with pytest.raises(InputFileError, match=r"bad.json: .*focal lengths must be positive"):
        CameraModel.from_json(bad)


def test_bad_parameters():
    with pytest.raises(ConfigurationError, match="4, 5, 8, 12 or 14"):
        CameraModel(640, 480, 500, 500, 320, 240, (0.1, 0.2, 0.3))
    with pytest.raises(ConfigurationError, match="skew"):
        CameraModel.from_opencv([[500, 1.5, 320], [0, 500, 240], [0, 0, 1]], None, (640, 480))
    with pytest.raises(ConfigurationError, match="positive integer"):
        CameraModel(0, 480, 500, 500, 320, 240)
    with pytest.raises(ConfigurationError, match="three finite numbers"):
        Mounting(baseline_mm=(1.0, 2.0))
    with pytest.raises(ConfigurationError, match=r"shape \(\.\.\., 3\)"):
        CAMERAS["pinhole"].project(np.zeros((4, 2)))


@pytest.mark.parametrize("name", ["real-calibration", "real-rational", "strong-barrel", "wide-rational",
                                  "thin-prism-tilted"])
def test_compiled_undistortion_is_the_array_iterations_point_by_point(name, monkeypatch):
    """The compiled Newton iterations (distortion_kernel) give the array version's results bit for bit: inside
    the image, beyond the monotonic radius (pulled in, stalled), and at non-finite input."""
    from omnispectral.imaging import geometry

    cam = CAMERAS.get(name) or CameraModel(**REAL_RATIONAL)
    rng = np.random.default_rng(7)
    xd = np.concatenate([rng.uniform(-1.6, 1.6, 6000), [np.nan, np.inf, 0.0, 3.0, -40.0]])
    yd = np.concatenate([rng.uniform(-1.2, 1.2, 6000), [0.0, 1.0, np.nan, 3.0, 0.1]])
    compiled = cam.undistort_normalized(xd, yd)
    monkeypatch.setattr(geometry, "_COMPILED_UNDISTORT_MIN", 10**12)
    array = cam.undistort_normalized(xd, yd)
    for c, a in zip(compiled, array, strict=True):
        assert np.array_equal(c, a, equal_nan=True)
    assert array[2].any() and not array[2].all()  # both converged and stalled points were compared


@pytest.mark.parametrize("name", ["real-calibration", "real-rational", "strong-barrel", "wide-rational",
                                  "thin-prism-tilted"])
def test_compiled_projection_is_the_array_projection(name, monkeypatch):
    """The compiled projection (distortion_kernel.compiled_project) gives the array version's pixels and validity
    bit for bit: inside and outside the image, behind the camera, beyond the monotonic radius, non-finite rays,
    with and without the image test."""
    from omnispectral.imaging import geometry

    cam = CAMERAS.get(name) or CameraModel(**REAL_RATIONAL)
    rng = np.random.default_rng(11)
    odd = [[0.0, 0.0, 0.0], [np.nan, 0.0, 1.0], [np.inf, 1.0, 1.0], [5.0, 5.0, 1.0], [0.0, 0.0, -1.0]]
    rays = np.concatenate([rng.normal(size=(5999, 3)) * [0.8, 0.6, 1.0] + [0.0, 0.0, 0.7], odd])
    rays = rays.reshape(2, -1, 3)
    for margin in (0.0, 3.5, None):
        compiled = cam.project(rays, margin_px=margin)
        monkeypatch.setattr(geometry, "_COMPILED_PROJECT_MIN", 10**12)
        array = cam.project(rays, margin_px=margin)
        monkeypatch.undo()
        assert compiled[0].shape == array[0].shape == (2, 3002, 2) and compiled[1].shape == (2, 3002)
        assert np.array_equal(compiled[0], array[0], equal_nan=True)
        assert np.array_equal(compiled[1], array[1])
        assert array[1].any() and not array[1].all()
