"""``omnispectral spectral evaluate | select-filters | list``: the arguments; run by
:mod:`omnispectral.cli.spectral`."""

from __future__ import annotations

import argparse

from omnispectral.choices import DEFAULT_CAMERA, DEFAULT_FILTERS, DEFAULT_ILLUMINANT, DEFAULT_TARGET
from omnispectral.cli.parsers import seed_arg

__all__ = ["add_commands"]


def _add_protocol_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--target", default=DEFAULT_TARGET,
                   help="reflectance set to evaluate: colorchecker (default), another built-in set or FILE.csv")
    p.add_argument("--illuminant", default=DEFAULT_ILLUMINANT,
                   help="light source of the target: D65 (default), A, FL11, LED-B3, D100, 5500K or FILE.csv")
    p.add_argument("--camera", default=DEFAULT_CAMERA,
                   help=f"camera RGB sensitivities: built-in name (default {DEFAULT_CAMERA!r}) or FILE.csv")
    p.add_argument("--noise", choices=["on", "off"], default="on",
                   help="simulate CMV2000 sensor noise (12 bit, 13500 e- full well, 13 e- read noise)")
    p.add_argument("--patch-px", type=int, default=32, help="side of the pixel region averaged per patch")
    p.add_argument("--seed", type=seed_arg, default=0, help="random seed of the noise simulation")
    p.add_argument("--estimator", choices=["mixture", "pooled"], default="mixture",
                   help="mixture: one prior component per light source (default); pooled: paper Eq. (7) as is")
    p.add_argument("--absolute", action="store_true",
                   help="Eq. (7) in absolute units instead of the exposure-equivariant normalized form")
    p.add_argument("--sigma2", type=float, default=None, help="fix the noise variance instead of tuning it")
    p.add_argument("--prior-set", action="append", default=None, metavar="NAME|FILE.csv",
                   help="reflectance set for the prior (repeat; replaces the built-in list; see 'spectral list')")
    p.add_argument("--prior-illuminant", action="append", default=None, metavar="NAME|FILE.csv",
                   help="light source for the prior (repeat; replaces the built-in nine)")


def add_commands(sub) -> None:
    """Register ``spectral evaluate | select-filters | list``."""

    spectral = sub.add_parser("spectral", help="six-band system, Wiener estimation, accuracy, filter selection",
                              description="Spectral core: six-band system, Wiener estimation (paper Eq. (7)).")
    ssub = spectral.add_subparsers(dest="spectral_command", metavar="SUBCOMMAND", required=True)

    ev = ssub.add_parser("evaluate", help="six-band vs RGB accuracy on a chart (paper Sec. 5.2)",
                         description="Reproduce paper Sec. 5.2: six-band vs RGB (same camera, no filters) "
                                     "spectral and colour accuracy on a chart under a light source.")
    _add_protocol_args(ev)
    ev.add_argument("--filter", action="append", default=None, metavar="NAME|FILE.csv",
                    help=f"filter of camera A then camera B (give twice; default {' + '.join(DEFAULT_FILTERS)})")
    ev.add_argument("--nonnegative", action="store_true", help="clip negative estimated spectral values to 0")
    ev.add_argument("--noise-aware", action="store_true",
                    help="give the estimator each patch's noise variance (signal-dependent sigma^2)")
    ev.add_argument("--plot", default=None, metavar="FILE.png|none",
                    help="also write a PNG of six estimated vs true spectra (paper Fig. 9 style) to FILE.png "
                         "(default: no plot; 'none' is accepted for no plot too)")
    ev.add_argument("--json", action="store_true", help="print results as JSON")
    ev.add_argument("--json-out", default=None, metavar="FILE.json", help="also write the JSON results to a file")
    ev.set_defaults(func="omnispectral.cli.spectral:cmd_spectral_evaluate")

    sel = ssub.add_parser("select-filters", help="exhaustive search for the best filter pair",
                          description="Score every pair of filters in a candidate table with the evaluation "
                                      "protocol and report the best pairs and where the reference pair ranks.")
    sel.add_argument("--candidates", required=True, metavar="FILE.csv",
                     help="transmittance table wavelength_nm,<filter>,... (percent or fraction, detected)")
    sel.add_argument("--top", type=int, default=10, help="how many pairs to report")
    sel.add_argument("--reference", nargs=2, default=list(DEFAULT_FILTERS), metavar=("A", "B"),
                     help="reference pair to rank (default: the paper's 34A + SP-18 stand-in)")
    sel.add_argument("--estimator", choices=["mixture", "pooled"], default="pooled",
                     help="estimator used to score pairs (default pooled: paper Eq. (7))")

    sel.add_argument("--camera", default=DEFAULT_CAMERA, help="camera sensitivities (name or FILE.csv)")
    sel.add_argument("--target", default=DEFAULT_TARGET, help="reflectance set to score on")
    sel.add_argument("--illuminant", default=DEFAULT_ILLUMINANT, help="light source of the target")
    sel.add_argument("--json", action="store_true", help="print results as JSON")
    sel.set_defaults(func="omnispectral.cli.spectral:cmd_spectral_select")

    ls = ssub.add_parser("list", help="list built-in cameras, filters, illuminants and reflectance sets")
    ls.add_argument("--json", action="store_true", help="print as JSON")
    ls.set_defaults(func="omnispectral.cli.spectral:cmd_spectral_list")
