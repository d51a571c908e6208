"""Refresh the viewer's vendored front-end files from npm at pinned versions.

Run by a developer (not at install or run time; ``pip install`` needs no node):

    python scripts/vendor_viewer.py

It runs ``npm install`` of the packages below into a temporary directory and copies their built ES
modules, stylesheets and licences into ``src/omnispectral/view/static/vendor/``, then writes
``vendor/VERSIONS.json`` (package, version, files, SHA-256).  Bump a version here and rerun.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "src" / "omnispectral" / "view" / "static" / "vendor"

#: npm package → (pinned version, {file in the package: name in vendor/<dir>/}, vendor sub-directory)
PACKAGES = {
    "three": ("0.185.1", {"build/three.module.min.js": "three.module.min.js",
                          "build/three.core.min.js": "three.core.min.js", "LICENSE": "LICENSE"}, "three"),
    "@photo-sphere-viewer/core": ("5.15.1", {"index.module.js": "index.module.js", "index.css": "index.css",
                                             "LICENSE": "LICENSE"}, "photo-sphere-viewer-core"),
    "@photo-sphere-viewer/equirectangular-tiles-adapter": (
        "5.15.1", {"index.module.js": "index.module.js", "LICENSE": "LICENSE"},
        "photo-sphere-viewer-equirectangular-tiles-adapter"),
}


def npm_install(workdir: Path) -> None:
    """``npm install`` the pinned packages (exact versions) into ``workdir/node_modules``."""
    specs = [f"{name}@{version}" for name, (version, _, _) in PACKAGES.items()]
    (workdir / "package.json").write_text(json.dumps({"name": "omnispectral-viewer-vendor", "private": True}))
    subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--save-exact", *specs], cwd=workdir, check=True)


def copy_files(workdir: Path) -> dict:
    """Copy the listed files into ``OUT`` and return the manifest written to VERSIONS.json."""
    if OUT.exists():
        shutil.rmtree(OUT)
    manifest = {}
    for name, (version, files, subdir) in PACKAGES.items():
        pkg = workdir / "node_modules" / name
        found = json.loads((pkg / "package.json").read_text())["version"]
        if found != version:
            sys.exit(f"npm installed {name} {found}, expected {version}")
        entry = {"version": version, "license": json.loads((pkg / "package.json").read_text()).get("license"),
                 "files": {}}
        for src, dst in files.items():
            target = OUT / subdir / dst
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(pkg / src, target)
            entry["files"][f"{subdir}/{dst}"] = hashlib.sha256(target.read_bytes()).hexdigest()
            print("vendored", target.relative_to(ROOT))
        manifest[name] = entry
    return manifest


def main() -> int:
    if shutil.which("npm") is None:
        sys.exit("npm is needed to refresh the vendored viewer files (apt-get install npm)")
    with tempfile.TemporaryDirectory(prefix="omnispectral-vendor-") as tmp:
        npm_install(Path(tmp))
        manifest = copy_files(Path(tmp))
    (OUT / "VERSIONS.json").write_text(json.dumps(manifest, indent=2) + "\n")
    print("wrote", (OUT / "VERSIONS.json").relative_to(ROOT))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
