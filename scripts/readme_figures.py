"""Rewrite README.md's "Accuracy end to end (`make demo` …)" figures from what the demo measures.

    python scripts/readme_figures.py                 # runs `omnispectral demo` in a temporary directory (~2 min)
    python scripts/readme_figures.py --report demo-output/report.json   # a demo already run on the current code
    python scripts/readme_figures.py --check         # exit 1 if the README's figures are not the demo's

The table's "demo (small sensors)" column (PSNR, spectral NRMSE, ColorChecker NRMSE and ΔE*ab, depth-edge errors,
holes, horizontal irradiance against the truth) and the paragraph under it ("N % of the pixels and N times the
band error") come from ``report.json``, formatted as ``omnispectral demo`` prints them.  The row "camera B at
infinity … against the true mounting" and "0.57 px fitted from the session's own images" are not in the demo's
report (docs/benchmarks.md measures them) and are left as they are.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SECTION = "## Accuracy end to end (`make demo`"


def figures(report: dict) -> dict[str, str]:
    """Table label (start of the measure cell) → the demo column's text."""
    acc = report["accuracy"]
    cc = acc.get("colorchecker") or {}
    out = {"six-band PSNR against ground truth": f"{acc['six_band_psnr_db']:.1f} dB",
           "spectral NRMSE, whole panorama": f"{acc['spectral_nrmse']:.4f}",
           "ColorChecker in the panorama: NRMSE": f"{cc['nrmse']:.4f}",
           "ColorChecker in the panorama: ΔE*ab mean / max": f"{cc['delta_e_ab']:.2f} / {cc['delta_e_ab_max']:.2f}"}
    edges = (acc.get("pixel_errors") or {}).get("depth_edges")
    if edges:
        e, s = edges["edge"], edges["smooth"]
        out["band NRMSE within"] = f"{e['band_nrmse']:.3f} / {s['band_nrmse']:.4f}"
        out["ΔE*ab (the pipeline's) within"] = f"{e['delta_e_ab']:.2f} / {s['delta_e_ab']:.2f}"
    if report.get("holes") is not None:
        out["holes: covered pixels with a band missing"] = f"{report['holes']['n_pixels']}"
    ratio = (report.get("irradiance") or {}).get("ratio_to_truth")
    if ratio:
        out["horizontal irradiance / the truth's"] = f"{min(ratio):.3f}–{max(ratio):.3f}"
    return out


def rewrite(text: str, report: dict) -> str:
    """``text`` (the README) with the demo's figures of ``report``."""
    start = text.index(SECTION)
    end = text.find("\n## ", start + len(SECTION))
    end = len(text) if end < 0 else end
    section = text[start:end]
    for label, value in figures(report).items():
        pattern = re.compile(r"^(\| " + re.escape(label) + r"[^|]*\| )[^|]*?( \|)", re.M)
        if not pattern.search(section):
            raise SystemExit(f"README: no row {label!r} in the section {SECTION!r}")
        section = pattern.sub(lambda m, v=value: m.group(1) + v + m.group(2), section, count=1)
    edges = (report["accuracy"].get("pixel_errors") or {}).get("depth_edges")
    if edges and edges["smooth"]["band_nrmse"]:
        share = f"{edges['edge_fraction'] * 100:.0f} %"
        times = f"{edges['edge']['band_nrmse'] / edges['smooth']['band_nrmse']:.0f}"
        section = re.sub(r"(they hold )\S+ %( of the pixels and )\S+( times the\s+band error)",
                         lambda m: f"{m.group(1)}{share}{m.group(2)}{times}{m.group(3)}", section)
    return text[:start] + section + text[end:]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--report", default=None, metavar="REPORT.json",
                    help="an existing demo's report.json (default: run the demo now, in a temporary directory)")
    ap.add_argument("--check", action="store_true", help="do not write: exit 1 if the README is stale")
    args = ap.parse_args(argv)
    if args.report:
        report = json.loads(Path(args.report).read_text())
    else:
        exe = Path(sys.executable).parent / "omnispectral"
        with tempfile.TemporaryDirectory() as tmp:
            subprocess.run([str(exe), "demo", "-o", tmp], check=True, stdout=subprocess.DEVNULL)
            report = json.loads((Path(tmp) / "report.json").read_text())
    text = README.read_text()
    new = rewrite(text, report)
    if new == text:
        print("README.md: the demo's figures are current")
        return 0
    if args.check:
        print("README.md: the demo's figures are stale (run scripts/readme_figures.py)")
        return 1
    README.write_text(new)
    print("README.md: the demo's figures updated")
    return 0


if __name__ == "__main__":
    sys.exit(main())
