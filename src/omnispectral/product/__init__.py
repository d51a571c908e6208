"""The product of a capture: the six-band panorama with its estimator, spectra on demand, exports, reports."""
