"""omnispectral: high-dynamic-range spectral imaging of omnidirectional scenes.

Implements and extends Hirai et al., "High-Dynamic-Range Spectral Imaging System for
Omnidirectional Scene Capture", J. Imaging 4(4):53, 2018: a six-band camera built from two
RGB cameras behind two colour filters on a pan/tilt head, HDR synthesis, registration,
omnidirectional mosaicking and Wiener estimation of spectra.
"""

from omnispectral.errors import ConfigurationError, InputFileError, OmnispectralError

__version__ = "0.1.0"

__all__ = ["ConfigurationError", "InputFileError", "OmnispectralError", "__version__"]
