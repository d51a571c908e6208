"""End to end in a real headless Chromium (Debian's ``chromium`` + ``chromium-driver``, driven by Selenium):
the viewer loads a processed product, renders it, a click gives the spectrum ``omnispectral spectrum`` gives at
the clicked direction, the exposure slider changes the pixels, a time slider loads another slot."""

from __future__ import annotations

import datetime as dt
import json
import shutil
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

pytest.importorskip("starlette", reason="starlette is not installed (pip install 'omnispectral[view]')")

from omnispectral.cli import main
from omnispectral.product.spectra import spectrum_at
from omnispectral.view.server import create_app
from tests.view.test_view import running_server

CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(CHROMIUM is None or CHROMEDRIVER is None,
                       reason="headless browser tests need Debian's chromium and chromium-driver "
                              "(apt-get install chromium chromium-driver; .ci/run installs them)"),
]
VIEW_W, VIEW_H = 1200, 700


@pytest.fixture(scope="module")
def driver():
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install selenium)")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={VIEW_W},{VIEW_H}",
                "--enable-unsafe-swiftshader", "--use-angle=swiftshader"):  # WebGL without a GPU
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})  # console messages for get_log
    d = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    yield d
    d.quit()


@pytest.fixture(scope="module")
def product(tmp_path_factory):
    """``omnispectral simulate --preset small`` + ``process``, as a user would (~25 s)."""
    root = tmp_path_factory.mktemp("viewe2e")
    assert main(["simulate", "--preset", "small", "--time", "12:00", "-o", str(root / "session")]) == 0
    assert main(["process", str(root / "session"), "-o", str(root / "product")]) == 0
    return root / "product"


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    """Two slots (07:00, 12:00) of the reduced rig through ``process-series``."""
    from omnispectral.capture.timelapse import slot_times
    from tests.product.test_product import simulate_series, tiny_rig

    root = tmp_path_factory.mktemp("viewseries")
    rig = tiny_rig()
    start = dt.datetime(2017, 6, 21, 7, 0, tzinfo=dt.UTC)
    slots = slot_times(start, start.replace(hour=12), 5 * 3600)
    simulate_series(root / "series", rig, slots)
    assert main(["process-series", str(root / "series"), "-o", str(root / "out"), "--json"]) == 0
    return root / "out"


# ------------------------------------------------------------------ helpers
def wait_for(driver, script: str, timeout_s: float = 60.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.1)
    errors = driver.execute_script("return window.omni && window.omni.errors")
    raise AssertionError(f"timed out waiting for {script!r}; viewer errors: {errors}")


def wait_tiles(driver, must_contain: str = "", settle_s: float = 1.0, timeout_s: float = 60.0) -> None:
    """Wait until tile requests containing ``must_contain`` were made and no request came for ``settle_s``."""
    script = ("return performance.getEntriesByType('resource').filter(e => e.name.includes('/api/') && "
              f"e.name.includes({json.dumps(must_contain)})).length")
    wait_for(driver, script, timeout_s)
    t0, last, n = time.monotonic(), time.monotonic(), -1
    while time.monotonic() - t0 < timeout_s:
        count = driver.execute_script("return performance.getEntriesByType('resource').length")
        if count != n:
            n, last = count, time.monotonic()
        elif time.monotonic() - last > settle_s:
            time.sleep(0.3)  # one more frame for the textures
            return
        time.sleep(0.1)


def viewer_pixels(driver) -> np.ndarray:
    from selenium.webdriver.common.by import By

    png = driver.find_element(By.ID, "viewer").screenshot_as_png
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return img[: img.shape[0] - 60]  # without PSV's navigation bar


def set_range(driver, element_id: str, value) -> None:
    driver.execute_script(f"const e = document.getElementById({json.dumps(element_id)}); e.value = arguments[0];"
                          "e.dispatchEvent(new Event('input')); e.dispatchEvent(new Event('change'));", str(value))


def open_viewer(driver, port: int, query: str = "lon=20&lat=-10&zoom=30") -> None:
    driver.get(f"http://127.0.0.1:{port}/?{query}")
    wait_for(driver, "return window.omni && window.omni.ready && window.omni.loads >= 1")
    wait_tiles(driver, "/api/tile/")


def click_viewer(driver, dx: int = 0, dy: int = 0, shift: bool = False) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    version = driver.execute_script("return window.omni.probeVersion || 0")
    chain = ActionChains(driver)
    if shift:
        chain = chain.key_down(Keys.SHIFT)
    chain = chain.move_to_element_with_offset(driver.find_element(By.ID, "viewer"), dx, dy).click()
    if shift:
        chain = chain.key_up(Keys.SHIFT)
    chain.perform()
    wait_for(driver, f"return (window.omni.probeVersion || 0) > {version}")


def cli_spectrum(product, lon: float, lat: float) -> dict:
    out = subprocess.run([sys.executable, "-m", "omnispectral.cli", "spectrum", str(product), "--lon", repr(lon),
                          "--lat", repr(lat), "--json"], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


# ------------------------------------------------------------------ tests
def test_viewer_renders_and_a_click_gives_the_spectrum_of_that_direction(driver, product):
    with running_server(create_app(product)) as port:
        open_viewer(driver, port)
        img = viewer_pixels(driver)
        # a rendered panorama, not a blank or single-colour canvas
        assert img.std() > 15 and 30 < img.mean() < 230
        assert len(np.unique(img.reshape(-1, 3) // 8, axis=0)) > 200
        click_viewer(driver)  # the centre of the view: lon 20°, lat -10°
        probe = driver.execute_script("return window.omni.probes[0]")
        # its marker sits where the click was (the centre of the viewer element)
        marker = driver.execute_script("const r = document.querySelector('.marker.p1').getBoundingClientRect();"
                                       "const v = document.getElementById('viewer').getBoundingClientRect();"
                                       "return [r.x + r.width / 2 - v.x - v.width / 2, r.y + r.height / 2 - v.y - "
                                       "v.height / 2]")
        assert np.hypot(*marker) < 3, marker
        assert "error" not in probe, probe
        # one pixel of the 1200-px-wide view at zoom 30 is well under 0.2°
        assert abs(probe["lon_deg"] - 20) < 0.2 and abs(probe["lat_deg"] + 10) < 0.2
        ref = cli_spectrum(product, probe["lon_deg"], probe["lat_deg"])
        np.testing.assert_allclose(probe["spectrum"], ref["spectrum"], rtol=1e-9, atol=0)
        np.testing.assert_allclose(probe["std"], ref["std"], rtol=1e-9, atol=0)
        assert probe["bands"].keys() == ref["bands"].keys()
        np.testing.assert_allclose([probe["bands"][k] for k in ref["bands"]], list(ref["bands"].values()), rtol=1e-12)
        x, y, z = ref["XYZ"]
        text = driver.execute_script("return document.getElementById('probe-text').textContent")
        assert f"CIE x {x / (x + y + z):.4g}" in text or f"CIE x {x / (x + y + z):.4f}" in text[:-1] + "0"
        # the chart is drawn and visible: a curve spanning most of the plot width, ±2σ band behind it
        width = driver.execute_script("return document.querySelector('#chart .curve').getBBox().width")
        assert width > 200
        assert driver.execute_script("return document.querySelectorAll('#chart polygon').length") == 1
        cells = driver.execute_script("return [...document.querySelectorAll('#bands-table td.p1')]"
                                      ".map(td => Number(td.textContent))")
        np.testing.assert_allclose(cells, list(ref["bands"].values()), rtol=1e-4)

        # exposure slider: +2 EV brightens, -2 EV darkens the same view
        before = viewer_pixels(driver).astype(float)
        set_range(driver, "ev", 2)
        wait_tiles(driver, "ev=2")
        brighter = viewer_pixels(driver).astype(float)
        set_range(driver, "ev", -2)
        wait_tiles(driver, "ev=-2")
        darker = viewer_pixels(driver).astype(float)
        assert brighter.mean() > before.mean() + 15 and darker.mean() < before.mean() - 15

        # shift-click: a second probe to the right; both in the CSV export
        click_viewer(driver, dx=100, shift=True)
        probes = driver.execute_script("return window.omni.probes")
        assert probes[1] is not None and 5 < probes[1]["lon_deg"] - probes[0]["lon_deg"] < 30
        csv_text = driver.execute_async_script(
            "const done = arguments[0]; fetch(document.getElementById('csv').href).then(r => r.text()).then(done);")
        assert "P2_estimate" in csv_text and f"lon_deg={probes[1]['lon_deg']:.6f}" in csv_text
        severe = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        assert not severe, severe


def test_display_modes_change_the_tiles(driver, product):
    with running_server(create_app(product)) as port:
        open_viewer(driver, port)
        colour = viewer_pixels(driver).astype(float)
        driver.execute_script("const m = document.getElementById('mode'); m.value = 'uncertainty';"
                              "m.dispatchEvent(new Event('change'));")
        wait_tiles(driver, "mode=uncertainty")
        unc = viewer_pixels(driver).astype(float)
        assert np.abs(unc - colour).mean() > 10
        # viridis: blue/green dominate red except at the top of the scale
        assert unc[..., 0].mean() > unc[..., 2].mean()  # OpenCV order: B > R


def test_time_slider_loads_another_slot_and_tracks_the_probe(driver, series):
    from omnispectral.product.series import series_products

    slots = series_products(series)
    with running_server(create_app(series)) as port:
        open_viewer(driver, port, "lon=30&lat=55&zoom=10")
        first = viewer_pixels(driver).astype(float)
        click_viewer(driver)
        wait_for(driver, "return window.omni.day && window.omni.day.length === 2")
        assert "error" not in driver.execute_script("return window.omni.probes[0]")
        set_range(driver, "time", 1)
        wait_tiles(driver, "t=1")
        wait_for(driver, "return window.omni.probes[0] && window.omni.probes[0].slot === 1")
        second = viewer_pixels(driver).astype(float)
        assert np.abs(second - first).mean() > 3  # 07:00 and 12:00 differ (sky, shadows, exposure)
        probe = driver.execute_script("return window.omni.probes[0]")
        assert "error" not in probe, probe
        day = driver.execute_script("return window.omni.day")
        # the view was kept: the probed direction is still the centre of the view
        pos = driver.execute_script("return window.omni.viewer.getPosition()")
        assert abs(np.degrees(pos["pitch"]) - 55) < 0.01
        for t, (_, path) in enumerate(slots):
            ref = spectrum_at(path, probe["lon_deg"], probe["lat_deg"])
            np.testing.assert_allclose(day[t]["spectrum"], ref["spectrum"], rtol=1e-9)
        np.testing.assert_allclose(probe["spectrum"], day[1]["spectrum"], rtol=1e-12)
        assert driver.execute_script("return document.querySelectorAll('#day-chart .curve').length") == 2
