"""GenICam driver through real harvesters calls on the simulated GenTL producer shipped in the ``genicam`` package."""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("harvesters", reason="harvesters is not installed (pip install 'omnispectral[devices]')")

from omnispectral.capture.devices import Camera, DeviceError, DeviceTimeout
from omnispectral.capture.drivers.gentl import (
    GenTLSystem,
    bits_of_pixel_format,
    cfa_pattern_of,
    frame_to_uint16,
    producer_paths,
    simulated_producer_path,
)
from omnispectral.errors import ConfigurationError, OmnispectralError


@pytest.fixture(scope="module")
def system():
    s = GenTLSystem(producer_paths(["simulator"], environment=False))
    yield s
    s.close()


def test_simulated_producer_ships_with_genicam():
    p = simulated_producer_path()
    assert p.name == "viky.cti" and p.stat().st_size > 100_000


def test_enumerate(system):
    devs = system.devices()
    assert [d["serial"] for d in devs] == ["0", "1", "2"]
    assert {d["model"] for d in devs} == {"Viky"}
    assert system.find(serial="2") == 2
    with pytest.raises(DeviceError, match=r"GenICam camera with user id 'left': not found \(cameras found: Viky"):
        system.find(user_id="left")  # the simulator's devices have no user-defined name


@pytest.mark.parametrize("serial,channel", [("0", 0), ("1", 1)])
def test_open_by_serial_and_acquire_rgb(system, serial, channel):
    """Device 0 draws a red ball, device 1 a green one, on white: the RGB channel order survives."""
    cam = system.open("A", serial=serial, width_px=320, height_px=240, bit_depth=8, fixed_exposure=True,
                      frame_rate_hz=100)
    try:
        assert isinstance(cam, Camera)
        assert cam.set_exposure(0.004) == 0.004  # no exposure feature: accepted because fixed_exposure
        centroids = []
        for _ in range(3):
            cam.trigger()
            frame, meta = cam.read_frame(timeout_s=2.0)
            assert frame.shape == (240, 320, 3) and frame.dtype == np.uint16
            assert meta["pixel_format"] == "RGBa8" and meta["serial"] == serial and meta["bit_depth"] == 8
            assert meta["exposure_controlled"] is False and "camera_timestamp_ns" not in meta
            others = [c for c in range(3) if c != channel]
            assert np.all(frame[..., channel] == 255)
            assert np.array_equal(frame[..., others[0]], frame[..., others[1]])
            ball = frame[..., others[0]] == 0
            assert 0.001 < ball.mean() < 0.5
            centroids.append(np.argwhere(ball).mean(axis=0))
        assert max(np.abs(centroids[i + 1] - centroids[i]).max() for i in range(2)) > 0.5  # new frames, ball moves
    finally:
        cam.close()


def test_mono8_and_missing_formats(system):
    cam = system.open("B", serial="2", pixel_format="Mono8", fixed_exposure=True)
    try:
        cam.trigger()
        frame, meta = cam.read_frame(2.0)
        assert frame.shape == (400, 400) and meta["pixel_format"] == "Mono8"
        assert set(np.unique(frame)) <= {0, 255} and (frame == 0).any() and (frame == 255).any()
    finally:
        cam.close()
    with pytest.raises(DeviceError, match=r"camera B \(.*serial 2\): pixel format 'BayerRG12' not offered "
                                          r"\(offers RGBa8, Mono8\)"):
        system.open("B", serial="2", pixel_format="BayerRG12", fixed_exposure=True)


def test_configuration_errors_are_one_line(system):
    cases = [
        (dict(serial="7"), DeviceError, r"serial '7': not found \(cameras found: Viky serial '0', Viky serial '1'"),
        (dict(serial="0"), DeviceError, r"no ExposureTime feature, so it cannot bracket exposures"),
        (dict(serial="0", bit_depth=12, fixed_exposure=True), ConfigurationError,
         r"rig says bit_depth 12 but pixel format RGBa8 has 8 bits"),
        (dict(serial="0", width_px=900, fixed_exposure=True), ConfigurationError,
         r"expects width 900 px, the camera gives 400 px"),
    ]
    for kwargs, kind, pattern in cases:
        with pytest.raises(kind, match=pattern) as ei:
            system.open("A", **kwargs)
        assert isinstance(ei.value, OmnispectralError) and "\n" not in str(ei.value)
    # every failed open released its device: it opens again
    system.open("A", serial="0", fixed_exposure=True).close()


def test_read_timeout_is_bounded(system):
    cam = system.open("A", serial="0", fixed_exposure=True, frame_rate_hz=1.0)
    try:
        cam.trigger()
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match=r"^camera A \(.*Viky serial 0\): no frame within 0.05 s$"):
            cam.read_frame(timeout_s=0.05)
        assert time.monotonic() - t0 < 0.5
    finally:
        cam.close()


def test_pixel_format_helpers():
    assert [bits_of_pixel_format(f) for f in ("Mono8", "BayerRG12", "BayerGB16", "Mono12p", "RGBa8")] == \
        [8, 12, 16, 12, 8]
    bgr = np.arange(2 * 3 * 3, dtype=np.uint8)
    out = frame_to_uint16(bgr, 3, 2, "BGR8")
    assert out.shape == (2, 3, 3) and out[0, 0].tolist() == [2, 1, 0]
    assert [cfa_pattern_of(f) for f in ("BayerRG12", "BayerGR8", "BayerGB16", "BayerBG10p", "Mono8")] == \
        ["RGGB", "GRBG", "GBRG", "BGGR", None]
    bayer = np.arange(12, dtype=np.uint16) * 300
    assert frame_to_uint16(bayer, 4, 3, "BayerRG12")[2, 3] == 3300


def test_a_camera_that_goes_away_is_a_disconnection_naming_it(system):
    """The device handle closed underneath the driver (GenTL ``DevClose``, as a producer does when the cable is
    pulled): the next trigger is a :class:`DeviceDisconnected` naming the camera (the capture loop stops
    cleanly and resumes later, as for a head's pulled cable), and closing the camera afterwards does not fail."""
    from omnispectral.capture.devices import DeviceDisconnected

    cam = system.open("A", serial="0", fixed_exposure=True)
    try:
        cam.trigger()
        frame, _ = cam.read_frame(timeout_s=2.0)
        assert frame.ndim == 3  # it worked before
        cam.ia.device.module.close()  # the real GenTL call: the device is gone
        with pytest.raises(DeviceDisconnected, match=r"^camera A \(.*serial 0\): trigger failed \(GenTL exception"):
            cam.trigger()
    finally:
        cam.close()
