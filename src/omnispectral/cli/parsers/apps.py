"""``omnispectral render | render-series | relight``: the arguments; run by :mod:`omnispectral.cli.apps`."""

from __future__ import annotations

from omnispectral.cli.parsers import seed_arg

__all__ = ["add_commands"]


def _add_render_args(p) -> None:
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="output directory")
    p.add_argument("--scene", default="mirror-ball", metavar="mirror-ball|FILE.xml",
                   help="the paper's mirror ball on a grey plate (default) or a Mitsuba scene file whose spectral "
                        "parameters are CSV files (<spectrum name=\"reflectance\" filename=\"paint.csv\"/>); the "
                        "file's film width/height and sampler sample_count are used unless --width, --height or "
                        "--spp is given")
    p.add_argument("--width", type=int, default=None, metavar="PX",
                   help="image width (default: a --scene file's film width, else 256; this option wins over the "
                        "scene file)")
    p.add_argument("--height", type=int, default=None, metavar="PX",
                   help="image height (default: a --scene file's film height, else 256; this option wins over the "
                        "scene file)")
    p.add_argument("--spp", type=int, default=None, metavar="N",
                   help="samples per pixel (default: a --scene file's sampler sample_count, else 64; this option "
                        "wins over the scene file)")
    p.add_argument("--level", type=int, default=None, help="pyramid level of the environment (default: the finest "
                                                            "at most --env-width wide)")
    p.add_argument("--env-width", type=int, default=1024, metavar="PX")
    p.add_argument("--wavelength-step", type=float, default=None, metavar="NM",
                   help="coarser spectral grid (default: the estimator's 5 nm, 61 wavelengths = 21 passes)")
    p.add_argument("--fast", action="store_true", help="six-band fast path (2 passes; exact only for "
                                                       "wavelength-flat materials)")
    p.add_argument("--view-lon", type=float, default=0.0, metavar="DEG", help="mirror ball: longitude the camera faces")
    p.add_argument("--elevation", type=float, default=15.0, metavar="DEG", help="mirror ball: camera elevation")
    p.add_argument("--metal", default=None, metavar="silver|aluminium|FILE.csv", help="mirror ball: the metal "
                                                                                       "(default silver)")
    p.add_argument("--variant", default=None, choices=["scalar_rgb", "llvm_ad_rgb"],
                   help="Mitsuba variant (default: llvm_ad_rgb when an LLVM library is installed)")
    p.add_argument("--seed", type=seed_arg, default=0)
    p.add_argument("--json", action="store_true")


def add_commands(sub) -> None:
    """Register ``render``, ``render-series`` and ``relight``."""
    r = sub.add_parser("render", help="spectral rendering lit by a product's panorama (Mitsuba 3)",
                       description="Image-based spectral rendering (paper Sec. 6.1): the product's spectral radiance "
                                   "as environment map, rendered by Mitsuba 3 three wavelengths per pass; writes a "
                                   "spectral EXR (Fichet 2021 layout), a linear sRGB EXR and a tone-mapped PNG.")
    r.add_argument("product", metavar="PRODUCT")
    _add_render_args(r)
    r.set_defaults(func="omnispectral.cli.apps:cmd_render")

    s = sub.add_parser("render-series", help="render every slot of a processed time-lapse (Fig. 16)",
                       description="Render each slot of a process-series output with the same scene; a frame "
                                   "sequence (frames/frame_0000.png …) and a labelled contact sheet.")
    s.add_argument("series", metavar="SERIES")
    _add_render_args(s)
    s.add_argument("--exposure", choices=["auto", "common"], default="auto",
                   help="tone-map each frame for itself, or all with the brightest slot's exposure")
    s.set_defaults(func="omnispectral.cli.apps:cmd_render_series")

    e = sub.add_parser("relight", help="relight a product to another illuminant from a white reference",
                       description="Spectral relighting (paper Sec. 6.2): the illuminant measured on white "
                                   "reference(s) in the scene, reflectance estimated per pixel under it, colour "
                                   "signals under the new illuminant; tile by tile into a product-like directory.")
    e.add_argument("product", metavar="PRODUCT")
    e.add_argument("--white", action="append", required=True, metavar="LON,LAT[,RADIUS_DEG]",
                   help="a white reference's direction (repeat for several; interpolated between them); write "
                        "--white=-30,0 when the longitude is negative")
    e.add_argument("--to", default="A", metavar="A|D65|FILE.csv", help="the new illuminant (default A)")
    e.add_argument("--white-reflectance", default=None, metavar="0.95|FILE.csv",
                   help="the white reference's reflectance (default flat 0.95)")
    e.add_argument("--sources", choices=["keep", "relight"], default="keep",
                   help="pixels brighter than the lit white (lamps, sky): keep as captured (default) or relight")
    e.add_argument("--source-factor", type=float, default=2.0, metavar="FACTOR",
                   help="a pixel is a light source above FACTOR times a perfect white's luminance under its light "
                        "(default 2: the illuminance varies over a room)")
    e.add_argument("--method", choices=["wiener", "ratio"], default="wiener",
                   help="reflectance by Wiener estimation under the measured light (default) or the paper's signal / "
                        "illuminant ratio")
    e.add_argument("-o", "--output", required=True, metavar="OUT")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func="omnispectral.cli.apps:cmd_relight")
