"""The paper's applications (Sec. 6): spectral image-based rendering and relighting of captured panoramas.

- :mod:`~omnispectral.apps.environment`: a product's spectral radiance as an environment map
  (estimator per pixel, never negative, saturated pixels flagged, uncovered pixels filled).
- :mod:`~omnispectral.apps.materials`: spectral materials (diffuse reflectances, metals from
  tabulated complex refractive indices) and the conductor Fresnel equations.
- :mod:`~omnispectral.apps.render`: Mitsuba 3 rendering, band-packed spectral (three wavelengths per
  RGB pass) and the six-band fast path; the mirror ball on a grey plate of Fig. 16.
- :mod:`~omnispectral.apps.relight`: relighting from a white reference (Sec. 6.2, Fig. 17), tile by
  tile into a product-like store.
"""

__all__: list[str] = []
