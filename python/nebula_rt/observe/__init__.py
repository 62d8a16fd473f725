"""What an observer sees and how it compares with what was observed.

- :mod:`~nebula_rt.observe.sky`: cameras and sky images (peel-off, ray marching);
- :mod:`~nebula_rt.observe.calibrate`: calibrated sky images (FITS with WCS, magnitudes, PNG);
- :mod:`~nebula_rt.observe.colours`: colour profiles of the scattered light against the star's;
- :mod:`~nebula_rt.observe.comparison`: models against observed tables (chi^2);
- :mod:`~nebula_rt.observe.image_compare`: models against observed images;
- :mod:`~nebula_rt.observe.observed_tables`, :mod:`~nebula_rt.observe.observed_images`: reading
  observations;
- :mod:`~nebula_rt.observe.published`: published dust albedo and g of real reflection nebulae
  and their illuminating stars (package data with provenance);
- :mod:`~nebula_rt.observe.fit`: fitting a scene's parameters to observations (:class:`FitRequest`), with
  :mod:`~nebula_rt.observe.fit_parameters` (what may be freed) and
  :mod:`~nebula_rt.observe.fit_surface` (the optimiser and its quadratic surface).

The names below are ``nebula_rt.observe``'s public API (the colour profiles).
"""

from .colours import delta_b_minus_v, observations, observe_scene

__all__ = ["delta_b_minus_v", "observations", "observe_scene"]
