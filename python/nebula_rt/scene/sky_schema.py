"""The sky image's parameters, declared once in the scene schema's style.

A sky image (Nebula Sky Image, :func:`nebula_rt.observe.sky.sky_image`) is made from a light field, not
from a scene file, so its parameters are not scene keys; they are declared here the way the
scene's are (:mod:`nebula_rt.scene.schema`): each field of :class:`SkyImageParameters` carries its
documentation, unit, range, label and panel group, and its default is the field's. The
camera's defaults (:class:`nebula_rt.observe.sky.Camera`), the VTK filter's setters
(``nebula_rt.filters.sky_image``) and the ParaView proxy's property XML are made from it.

Keys are ``"sky.<field>"``. This module never imports VTK.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple, Union

from . import schema
from .schema import document, param

__all__ = ["SkyImageParameters", "SECTIONS", "parameters", "declaration", "default", "validate_exposure"]

G_CAMERA, G_PICTURE = "Camera", "Picture"
#: The largest side of a sky image (pixels): a 16384^2 image of 3 bands is 6 GiB of float64
#: sums on the device, about what one GPU gives a peel-off image beside its grid
MAX_SKY_SIZE = 16384

#: pixels per side of a comparison's peel-off image (the annulus profiles of ``nebula-rt
#: compare``, the observed tables and images, the fits): a smaller default than a picture's,
#: since the rings sum many pixels and a fit traces the scene many times
COMPARISON_SIZE = 128


@document
@dataclass
class SkyImageParameters:
    """What a telescope far away sees: the camera and the picture of a sky image."""

    direction: Tuple[float, float, float] = param(
        (0.0, 0.0, -1.0), type="tuple of 3 float", label="View Direction", group=G_CAMERA,
        doc="Direction the telescope looks in, from the observer into the box (any non-zero length)")
    up: Tuple[float, float, float] = param(
        (0.0, 1.0, 0.0), type="tuple of 3 float", label="View Up", group=G_CAMERA,
        doc="Up direction of the image (its part perpendicular to the view direction; a box axis if "
            "it is parallel to it)")
    size: Tuple[int, int] = param(
        (256, 256), type="tuple of 2 int", lo=1, hi=MAX_SKY_SIZE, unit="pixels", label="Image Size", group=G_CAMERA,
        doc="Width and height of the image, the same range for the filter, ParaView's panel and "
            "nebula-rt's --size")
    extent: float = param(
        0.0, type="float", lo=0.0, unit="box units", group=G_CAMERA,
        doc="Width of the field of view; 0 fits the whole box whatever the direction (sqrt(3))")
    include_stars: bool = param(
        True, type="bool", label="Include Stars", group=G_PICTURE,
        doc="Add each star's attenuated direct light to the pixel it falls in")
    exposure: Union[float, str] = param(
        "auto", type="\"auto\" or float", lo=0.0, lo_open=True, auto=True, number=1.0, group=G_PICTURE,
        doc="Factor applied to the linear colour before the sRGB curve; \"auto\": the one that maps the "
            "99th percentile of the scattered light's brightest colour component to full scale (the stars "
            "saturate)")


#: The declared tables (one: ``sky``), as :data:`nebula_rt.scene.SECTIONS`.
SECTIONS = (("sky", SkyImageParameters),)


#: the sky-image keys' lookups: parameters(), declaration("sky.direction"), default(key)
parameters, declaration, default = (getattr(schema.Declarations(SECTIONS), n)
                                    for n in ("parameters", "declaration", "default"))


def validate_exposure(value) -> Union[float, str]:
    """``"auto"``, or the exposure as a float: a number > 0 within float32 (the colours are
    float32), the rule of the scene's ``colour.exposure``; SceneError naming ``sky.exposure``."""
    from .rules import COLOUR_RULES

    rule = COLOUR_RULES["exposure"]
    rule.validate("sky.exposure", value)
    return rule.coerce("sky.exposure", value)
