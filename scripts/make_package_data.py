"""Regenerate the small data files shipped inside the package from ../shared/data.

Run by a developer (not at install or run time):  python scripts/make_package_data.py
Only permissively licensed data are written (see src/omnispectral/data/README.md).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import scipy.io

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
OUT = ROOT / "src" / "omnispectral" / "data"


def write_csv(path: Path, wavelength_nm, columns: dict[str, np.ndarray], comment: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        for line in comment.strip().splitlines():
            fh.write(f"# {line}\n")
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["wavelength_nm", *columns])
        for j, wl in enumerate(wavelength_nm):
            w.writerow([f"{wl:g}", *(f"{col[j]:.6g}" for col in columns.values())])
    print("wrote", path.relative_to(ROOT))


WRATTEN_SOURCE = ("Source: Kodak publication 'Kodak Wratten Filters for Scientific and Technical Use' "
                  "(A. C. Peed Jr.),\nas tabulated in m-lohmann/SpectralVis.jl (MIT) data/spectra/spectrum_Wratten.jl")


def wratten_column(column: str, file_name: str, label: str, description: str) -> None:
    """One filter of the Wratten table (percent, 400-700 nm / 10 nm) as a package CSV."""
    src = SHARED / "filter_transmittance" / "wratten_visible_400-700nm_10nm_percent.csv"
    with open(src) as fh:
        rows = list(csv.reader(fh))
    header, data = rows[0], np.array(rows[1:], dtype=float)
    write_csv(OUT / "filters" / file_name, data[:, 0], {label: data[:, header.index(column)]}, description)


def wratten_34a() -> None:
    wratten_column("34A", "wratten_34a.csv", "Wratten 34A",
                   "Kodak Wratten No. 34A (violet) spectral transmittance in PERCENT, 400-700 nm / 10 nm.\n"
                   + WRATTEN_SOURCE + ".")


def wratten_96() -> None:
    wratten_column("96", "wratten_96.csv", "Wratten 96 (ND 1.0)",
                   "Kodak Wratten No. 96 neutral density 1.0 spectral transmittance in PERCENT, 400-700 nm / 10 nm.\n"
                   + WRATTEN_SOURCE + "; column '96'\nidentified as ND 1.0 by its flat ~9 % transmittance "
                   "(shared/data/filter_transmittance/SOURCE.txt).")


def vrhel() -> None:
    folder = SHARED / "reflectance" / "vrhel_isetcam"
    sets = {"vrhel_objects": "Objects_Vhrel.mat", "vrhel_munsell": "MunsellSamples_Vhrel.mat",
            "vrhel_dupont": "DupontPaintChip_Vhrel.mat"}
    for key, fname in sets.items():
        m = scipy.io.loadmat(folder / fname)
        wl = np.ravel(m["wavelength"]).astype(float)
        data = np.asarray(m["data"], dtype=float)
        comment = str(np.ravel(m["comment"])[0]) if "comment" in m else ""
        cols = {f"{key}_{i + 1:03d}": data[:, i] for i in range(data.shape[1])}
        write_csv(
            OUT / "reflectances" / f"{key}.csv", wl, cols,
            f"Vrhel, Gershon & Iwan (1994) measured surface reflectances, fraction, 400-700 nm / 10 nm.\n"
            f"ISETCam data/surfaces/reflectances/{fname} (MIT licence). {comment}",
        )


if __name__ == "__main__":
    wratten_34a()
    wratten_96()
    vrhel()
