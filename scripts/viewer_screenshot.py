"""Regenerate docs/viewer.png: the viewer on a product with two probes, in headless Chromium.

Run by a developer after ``make demo`` (needs Debian's chromium and chromium-driver, and selenium):

    python scripts/viewer_screenshot.py demo-output/product docs/viewer.png
"""

from __future__ import annotations

import socket
import sys
import threading
import time
from pathlib import Path

from PIL import Image
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By
from selenium.webdriver.common.keys import Keys

from omnispectral.view.server import create_app


def main(product: str, out: str, lon: float = 12.0, lat: float = -8.0) -> int:
    import uvicorn

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(create_app(product), host="127.0.0.1", port=port, log_level="error"))
    threading.Thread(target=server.run, daemon=True).start()
    while not server.started:
        time.sleep(0.05)
    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for arg in ("--headless=new", "--no-sandbox", "--window-size=1200,640", "--enable-unsafe-swiftshader",
                "--use-angle=swiftshader"):
        opts.add_argument(arg)
    d = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)
    try:
        d.get(f"http://127.0.0.1:{port}/?lon={lon}&lat={lat}&zoom=25")
        while not d.execute_script("return window.omni && window.omni.loads >= 1"):
            time.sleep(0.1)
        time.sleep(3)
        viewer = d.find_element(By.ID, "viewer")
        ActionChains(d).move_to_element_with_offset(viewer, -150, -80).click().perform()
        time.sleep(1)
        ActionChains(d).key_down(Keys.SHIFT).move_to_element_with_offset(viewer, 60, 150).click() \
            .key_up(Keys.SHIFT).perform()
        time.sleep(2)
        d.save_screenshot(out)
    finally:
        d.quit()
        server.should_exit = True
    Image.open(out).convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT).save(out, optimize=True)
    print(f"wrote {out} ({Path(out).stat().st_size // 1024} KiB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:3]))
