"""Readers for the real measured data in ../shared/data (test-only: not shipped, some non-commercial)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnispectral.spectral.curves import SpectralSet, write_spectral_csv


def camspec_cameras(path: Path) -> dict[str, np.ndarray]:
    """Jiang et al. 2013 camspec database: name line then R, G, B lines of 33 values (400-720/10 nm)."""
    lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines()]
    out = {}
    i = 0
    while i < len(lines):
        parts = lines[i].split()
        if lines[i] and i + 3 < len(lines) and len(lines[i + 1].split()) == 33 and len(parts) != 33:
            out[lines[i]] = np.array([[float(v) for v in lines[i + k].split()] for k in (1, 2, 3)])
            i += 4
        else:
            i += 1
    return out


def camspec_csv(path: Path, name: str, out_dir: Path) -> Path:
    cams = camspec_cameras(path)
    wl = np.arange(400.0, 721.0, 10.0)
    s = SpectralSet(wl, cams[name], ["R", "G", "B"], "sensitivity", name)
    return write_spectral_csv(s, out_dir / f"{name.replace(' ', '_')}.csv", comment=f"camspec {name}")


def joensuu_natural(path: Path) -> SpectralSet:
    """218 natural reflectances, raw 12-bit AOTF counts (normalised by 4096, clipped), 400-700/5 nm."""
    lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    rows, cur, expecting_label = [], [], True
    for ln in lines:
        if expecting_label:
            expecting_label = False
            continue
        cur += [float(t) for t in ln.split()]
        if len(cur) >= 61:
            rows.append(cur[:61])
            cur, expecting_label = [], True
    names = [f"joensuu_{i + 1:03d}" for i in range(len(rows))]
    vals = np.clip(np.array(rows) / 4096.0, 0, 1)
    return SpectralSet(np.arange(400.0, 701.0, 5.0), vals, names, "reflectance", "joensuu-natural")
