"""Dust and light: the bands and their dust optics (:mod:`~nebula_rt.optics.bands`), the
tabulated dust models (:mod:`~nebula_rt.optics.dust_tables`) and colour conversion with
colour-science (:mod:`~nebula_rt.optics.colour_convert`)."""
