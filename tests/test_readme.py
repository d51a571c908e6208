"""Every command line of README.md's ```sh blocks, run as written, in order, in one fresh directory.

The README's examples name files a user brings (``my_camera.csv``, ``memorial00*.png``, ``rig.toml``, ``a.pto``,
``session2/``…); :func:`make_user_files` makes stand-ins for them from the package's data, its simulator and
``../shared/data`` before the first line runs.  ``make …`` lines are not run (the CI runs them); ``make demo`` is
stood in for by ``omnispectral demo`` (the README's later lines read ``demo-output/``).  ``omnispectral view …``
starts a server that runs until interrupted: the test starts it, waits until it answers on
http://127.0.0.1:8000/ and stops it (``BROWSER=true``: ``--open`` opens no browser).  Each line must exit 0 (or
the status in :data:`EXIT`), and where the README states a result (files written, JSON keys, a CSV header)
:data:`CHECKS` looks at it.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SHARED = ROOT.parent / "shared" / "data"
BIN = Path(sys.executable).parent

#: lines not run as written, with why (matched by their start)
SKIP: dict[str, str] = {
    "make ": "the CI runs the Makefile itself (make demo is stood in for by `omnispectral demo`)",
}
#: exit statuses other than 0 that the README states for a line (matched by their start); none today: the
#: ``capture --dry-run`` line exits 1 only on a rig with problems, and the README's rig.toml (all simulated) has none
EXIT: dict[str, int] = {}


def sh_lines(text: str) -> list[str]:
    """The command lines of the ```sh blocks, in order."""
    lines = []
    for block in re.findall(r"^```sh\n(.*?)^```", text, flags=re.S | re.M):
        lines += [ln.strip() for ln in block.splitlines() if ln.strip() and not ln.strip().startswith("#")]
    return lines


def _files(path: Path) -> list[str]:
    return sorted(p.name for p in path.iterdir())


def _json_keys(*keys):
    def check(cwd: Path, out: str) -> None:
        data = json.loads(out)
        missing = [k for k in keys if k not in data]
        assert not missing, f"JSON lacks {missing}: {sorted(data)}"
    return check


def _exists(*names):
    def check(cwd: Path, out: str) -> None:
        missing = [n for n in names if not (cwd / n).exists()]
        assert not missing, f"not written: {missing}"
    return check


def _register(cwd: Path, out: str) -> None:
    r = json.loads(out)
    assert {"dx", "dy", "confidence"} <= set(r), r
    assert abs(abs(r["dx"]) - 3.25) < 0.2 and abs(abs(r["dy"]) - 1.5) < 0.2, r  # the shift make_user_files applied


def _spectrum_csv(cwd: Path, out: str) -> None:
    lines = (cwd / "spectrum.csv").read_text().splitlines()
    assert lines[0] == "wavelength_nm,spectrum,std", lines[0]
    assert len(lines) == 62, len(lines)  # 400-700 nm / 5 nm


#: what the README says a line gives (matched by their start)
CHECKS = {
    "omnispectral spectral evaluate --illuminant A --json": lambda cwd, out: json.loads(out),
    "omnispectral hdr merge memorial00": _exists("memorial.exr"),
    "omnispectral hdr merge raw_": _exists("merged.exr"),
    "omnispectral calibrate lens": _exists("lens.json"),
    "omnispectral register a.png b.png --json": _register,
    "omnispectral plan --preset paper-gigapixel": _exists("tradeoff.png"),
    "omnispectral simulate --preset small --time": _exists("session/ground_truth", "session/calibration"),
    "omnispectral simulate --preset small --raw": _exists("raw-session"),
    "omnispectral import --rig rig.toml --camera A": _exists("imported"),
    "omnispectral import --rig dslr.toml": _exists("dslr"),
    "omnispectral simulate --preset small --one-camera": _exists("rgb-session"),
    "omnispectral timelapse": _exists("series/calibration"),
    "omnispectral process session/ -o product/ ": _exists("product/product.json"),
    "omnispectral calibrate rig session/": _exists("rig-cal.json"),
    "omnispectral simulate-chessboard": _exists("boards"),
    "omnispectral process session2/": _exists("product2/product.json"),
    "omnispectral process session/ -o product-paper/": _exists("product-paper/product.json"),
    "omnispectral spectrum product/ --lon 30 --lat -15 --json": _json_keys("wavelength_nm", "spectrum", "std"),
    "omnispectral spectrum product/ --lon 30 --lat -15 --csv": _spectrum_csv,
    "omnispectral export product/ --format spectral-exr -o pano.exr": _exists("pano.exr", "pano_saturated.png"),
    "omnispectral export product/ --format spectral-exr -o pano-half.exr": _exists("pano-half.exr"),
    "omnispectral export product/ --format png": _exists("preview.png"),
    "omnispectral product verify product/": lambda cwd, out: None if "all good" in out else pytest.fail(out),
    "omnispectral process-series": _exists("series-out"),
    "omnispectral mosaic": _exists("pano.zarr"),
    "omnispectral render demo-output/product": _exists("ball"),
    "omnispectral render product/": _exists("out"),
    "omnispectral render-series": _exists("frames"),
    "omnispectral relight": _exists("relit"),
    "omnispectral simulate --scene indoor --light": _exists("room"),
    "omnispectral simulate --scene indoor --cube": _exists("room2"),
}

ROOM_XML = """<scene version="3.0.0">
    <sensor type="perspective">
        <float name="fov" value="45"/>
        <transform name="to_world"><lookat origin="0, 1, 4" target="0, 0.5, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
    </sensor>
    <shape type="sphere"><point name="center" value="0, 0.5, 0"/><float name="radius" value="0.5"/>
        <bsdf type="diffuse"/></shape>
</scene>
"""


def run(line: str, cwd: Path, env: dict, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-c", line], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def make_user_files(cwd: Path, env: dict) -> None:
    """Stand-ins for the files the README's examples name as the user's own."""
    import datetime as dt

    import tifffile
    from PIL import Image
    from scipy.ndimage import gaussian_filter, shift

    from omnispectral.rig import load_preset, one_camera_rig, rig_toml
    from omnispectral.sim.photographs import write_photographs
    from omnispectral.sim.scenes import DEFAULT_DATE, build_scene
    from omnispectral.spectral.curves import concatenate, write_spectral_csv
    from omnispectral.spectral.library import load_camera, load_filter

    data = ROOT / "src" / "omnispectral" / "data"
    write_spectral_csv(load_camera(), cwd / "my_camera.csv")
    shutil.copy(data / "filters" / "wratten_34a.csv", cwd / "my_filter.csv")
    candidates = [load_filter(n) for n in ("wratten-34a", "wratten-96", "sp18-standin")]  # candidate filters
    write_spectral_csv(concatenate(candidates, candidates[0].wavelength_nm), cwd / "filters.csv")
    shutil.copy(data / "reflectances" / "vrhel_objects.csv", cwd / "my_reflectances.csv")
    memorial = SHARED / "hdr_brackets" / "memorial_debevec1997"
    for p in [*sorted(memorial.glob("memorial00*.png")), memorial / "memorial.hdr_image_list.txt"]:
        shutil.copy(p, cwd / p.name)
    for p in sorted((SHARED / "calibration_chessboard").glob("left*.jpg")):
        shutil.copy(p, cwd / p.name)
    rng = np.random.default_rng(0)
    scene = rng.random((200, 300, 3))  # a 12-bit raw bracket of one scene: halved exposures
    for k, t in enumerate((0.252, 0.126, 0.063)):
        tifffile.imwrite(cwd / f"raw_{k}.tif", np.clip(scene * 4095 * t / 0.252 * 1.5, 0, 4095).astype(np.uint16))
    texture = gaussian_filter(rng.random((256, 256)), 2.0)
    texture = (texture - texture.min()) / np.ptp(texture)
    Image.fromarray((texture * 255).astype(np.uint8)).save(cwd / "a.png")
    Image.fromarray((shift(texture, (1.5, 3.25), mode="wrap") * 255).astype(np.uint8)).save(cwd / "b.png")
    # the rig file: the small preset (all-simulated devices, so capture runs the simulator)
    shutil.copy(data / "rigs" / "small.toml", cwd / "rig.toml")
    rig = load_preset("small")
    start = dt.datetime.combine(DEFAULT_DATE, dt.time(12), tzinfo=dt.UTC)
    procedural = build_scene("procedural", None, start, seed=0)
    a = write_photographs(cwd, rig, procedural, "A", fmt="jpeg")  # JPEG brackets with EXIF and a Hugin project
    shutil.move(a["pto"], cwd / "a.pto")
    b = write_photographs(cwd / "b", rig, procedural, "B", fmt="tiff")  # 16-bit TIFFs, Papywizard XML, times
    shutil.move(b["papywizard"], cwd / "b.xml")
    shutil.move(b["exposures"], cwd / "b.csv")
    for f in (a["papywizard"], a["csv"], b["pto"], b["csv"]):
        Path(f).unlink()
    # a one-camera rig (camera A alone, the same camera): dslr.toml, and its photographs are camera A's above
    (cwd / "dslr.toml").write_text(rig_toml(one_camera_rig(rig)))
    shutil.copy(cwd / "a.pto", cwd / "shots.pto")
    # a second session (another time of day), a reflectance cube
    r = run("omnispectral simulate --preset small --time 15:00 -o session2/", cwd, env)
    assert r.returncode == 0, r.stderr
    cube = np.clip(gaussian_filter(rng.random((24, 32, 31)), 1.5) * 2 - 0.5, 0.02, 0.98)
    np.savez(cwd / "paint.npz", cube=cube.astype(np.float32), wavelength_nm=np.arange(400.0, 701.0, 10.0))
    (cwd / "room.xml").write_text(ROOM_XML)


def wait_for_server(line: str, cwd: Path, env: dict, url: str = "http://127.0.0.1:8000/", limit: float = 120):
    proc = subprocess.Popen(["bash", "-c", f"exec {line}"], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < limit:
            if proc.poll() is not None:
                pytest.fail(f"{line!r} exited {proc.returncode}: {proc.stderr.read()[-2000:]}")
            try:
                with urllib.request.urlopen(url, timeout=5) as resp:
                    assert resp.status == 200
                    return
            except OSError:
                time.sleep(1)
        pytest.fail(f"{line!r} did not answer on {url} within {limit:.0f} s")
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


@pytest.mark.slow
@pytest.mark.long  # 8–13 min: make test-long (CI runs it after make test)
def test_readme_command_lines_run_as_written(tmp_path: Path) -> None:
    if not SHARED.is_dir():
        pytest.skip(f"shared data not found at {SHARED} (the Memorial bracket and the chessboard photos)")
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "BROWSER": "true"}
    lines = sh_lines(README.read_text())
    assert len(lines) > 40
    make_user_files(tmp_path, env)
    # `make demo` (not run): its product is what the README's later lines read
    r = run("omnispectral demo -o demo-output/", tmp_path, env)
    assert r.returncode == 0, r.stderr[-3000:]
    skipped, t0 = [], time.monotonic()
    for line in lines:
        reason = next((why for start, why in SKIP.items() if line.startswith(start)), None)
        if reason:
            skipped.append((line, reason))
            continue
        if line.startswith("omnispectral view "):
            wait_for_server(line, tmp_path, env)
            continue
        r = run(line, tmp_path, env)
        want = next((code for start, code in EXIT.items() if line.startswith(start)), 0)
        assert r.returncode == want, f"{line!r} exited {r.returncode} (README: {want}):\n{r.stderr[-3000:]}"
        check = next((c for start, c in CHECKS.items() if line.startswith(start)), None)
        if check is not None:
            check(tmp_path, r.stdout)
    print(f"{len(lines) - len(skipped)} lines run in {time.monotonic() - t0:.0f} s; skipped: {skipped}")
