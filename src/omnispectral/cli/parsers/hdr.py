"""``omnispectral hdr merge``: the arguments; run by :mod:`omnispectral.cli.hdr`."""

from __future__ import annotations

from omnispectral.choices import HDR_WEIGHT_NAMES

__all__ = ["add_commands"]


def add_commands(sub) -> None:
    """Register ``hdr merge``."""
    hdr = sub.add_parser("hdr", help="HDR synthesis from exposure brackets (paper Sec. 4.1)",
                         description="HDR synthesis from exposure brackets (paper Sec. 4.1, Eqs. (1)-(2)).")
    hsub = hdr.add_subparsers(dest="hdr_command", metavar="SUBCOMMAND", required=True)
    m = hsub.add_parser("merge", help="merge a bracket of raw or JPEG/PNG frames into an HDR image",
                        description="Merge an exposure bracket into linear radiance per second. Raw 12/16-bit "
                                    "frames (TIFF/PNG) are linear; 8-bit JPEG/PNG brackets get their camera "
                                    "response recovered (Debevec & Malik 1997). Exposure times come from --times, "
                                    "--times-list or EXIF, in that order.")
    m.add_argument("files", nargs="+", metavar="FILE", help="frames of one bracket (any order)")
    m.add_argument("--times", nargs="+", default=None, metavar="S",
                   help="exposure time of each file in seconds, in file order (0.004 or 1/250)")
    m.add_argument("--times-list", default=None, metavar="FILE.txt",
                   help="list file 'name seconds' per line (Debevec's hdr_image_list.txt format)")
    m.add_argument("--bit-depth", type=int, default=None,
                   help="bits per sample of the frames (default: 8 for 8-bit files, else guessed from the data)")
    m.add_argument("--weight", choices=["auto", *HDR_WEIGHT_NAMES], default="auto",
                   help="triangle: paper Eq. (2); noise: inverse variance (Granados 2010); auto: triangle for "
                        "linear frames, noise after response recovery")
    m.add_argument("--response", default="auto", metavar="auto|linear|debevec|FILE.json",
                   help="camera response: recover (debevec), linear, a saved response, or auto (default)")
    m.add_argument("--save-response", default=None, metavar="FILE.json", help="write the response used")
    m.add_argument("--deghost", action="store_true",
                   help="detect moving objects (exposures disagreeing beyond noise) and take them from one exposure")
    m.add_argument("--reference", type=int, default=None, metavar="K",
                   help="reference exposure for --deghost (index in file order; default the middle exposure time)")
    m.add_argument("--with-variance", action="store_true",
                   help="also store per-pixel variance and a validity channel (EXR/TIFF/NPY)")
    m.add_argument("--memory-gb", type=float, default=None, metavar="GB",
                   help="memory the merge may use (GiB); default half of the memory available. A bracket needing "
                        "more is refused from its headers, before decoding")
    m.add_argument("-o", "--output", required=True, metavar="OUT.exr", help="output .exr, .hdr, .tif or .npy")
    m.add_argument("--json", action="store_true", help="print a JSON summary")
    m.set_defaults(func="omnispectral.cli.hdr:cmd_hdr_merge")
