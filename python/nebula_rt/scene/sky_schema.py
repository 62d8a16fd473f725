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

import math
from dataclasses import dataclass
from typing import Tuple, Union

from . import schema
from .schema import document, param

__all__ = ["SkyImageParameters", "SECTIONS", "parameters", "declaration", "default", "validate_exposure",
           "valid_direction"]

G_CAMERA, G_PICTURE, G_VECTORS = "Camera", "Picture", "Polarization vectors"
#: The largest side of a sky image (pixels): a 16384^2 image of 3 bands is 6 GiB of float64
#: sums on the device, about what one GPU gives a peel-off image beside its grid
MAX_SKY_SIZE = 16384

#: pixels per side of a comparison's peel-off image (the annulus profiles of ``nebula-rt
#: compare``, the observed tables and images, the fits): a smaller default than a picture's,
#: since the rings sum many pixels and a fit traces the scene many times
COMPARISON_SIZE = 128

#: A direction (``sky.direction``, ``sky.up``, ``nebula-rt --direction``) is normalised in float64
#: as v / sqrt(x^2 + y^2 + z^2): its squares must neither overflow (1e308 along x and y made the
#: camera's basis NaN) nor vanish below float64's smallest normal number, 2.2e-308 (1e-320 along x
#: was divided by a length of 0). Components at most 1e150 in magnitude and a length of at least 1e-150 keep
#: every square that matters within [3e-301, 1e300].
MAX_DIRECTION_COMPONENT = 1e150
MIN_DIRECTION_LENGTH = 1e-150
_BIG, _SMALL = (f"{x:.0e}".replace("e+", "e") for x in (MAX_DIRECTION_COMPONENT, MIN_DIRECTION_LENGTH))
DIRECTION_ALLOWED = (f"must be 3 finite numbers x, y, z, each in [-{_BIG}, {_BIG}], of length "
                     f"sqrt(x^2 + y^2 + z^2) at least {_SMALL} (the direction is normalised in float64, whose "
                     "squares must neither overflow nor underflow)")


def valid_direction(v) -> bool:
    """``v`` (3 numbers) is a direction that normalises in float64 (:data:`DIRECTION_ALLOWED`);
    its length is taken with ``math.hypot``, which neither overflows nor underflows."""
    try:
        x = [float(c) for c in v]
    except (TypeError, ValueError):
        return False
    return (len(x) == 3 and all(math.isfinite(c) and abs(c) <= MAX_DIRECTION_COMPONENT for c in x)
            and math.hypot(*x) >= MIN_DIRECTION_LENGTH)


@document
@dataclass
class SkyImageParameters:
    """What a telescope far away sees: the camera and the picture of a sky image."""

    direction: Tuple[float, float, float] = param(
        (0.0, 0.0, -1.0), type="tuple of 3 float", lo=-MAX_DIRECTION_COMPONENT, hi=MAX_DIRECTION_COMPONENT,
        label="View Direction", group=G_CAMERA, check=valid_direction, allowed=DIRECTION_ALLOWED,
        doc=f"Direction the telescope looks in, from the observer into the box (any length from {_SMALL})")
    up: Tuple[float, float, float] = param(
        (0.0, 1.0, 0.0), type="tuple of 3 float", lo=-MAX_DIRECTION_COMPONENT, hi=MAX_DIRECTION_COMPONENT,
        label="View Up", group=G_CAMERA, check=valid_direction, allowed=DIRECTION_ALLOWED,
        doc="Up direction of the image (its part perpendicular to the view direction; a box axis if "
            "it is parallel to it)")
    size: Tuple[int, int] = param(
        (256, 256), type="tuple of 2 int", lo=1, hi=MAX_SKY_SIZE, unit="pixels", label="Image Size", group=G_CAMERA,
        doc="Width and height of the image, the same range for the filter, ParaView's panel and "
            "nebula-rt's --size")
    extent: float = param(
        0.0, type="float", lo=0.0, unit="box units", group=G_CAMERA,
        doc="Width of the field of view; 0 fits the whole box whatever the direction (sqrt(3))")
    method: str = param(
        "ray-march", type="str", choices=("ray-march", "peel-off"), label="Method", group=G_CAMERA,
        doc="ray-march: integrate the light field's emissivity along each pixel's ray (isotropic per "
            "voxel; fast, from the finished light field); peel-off: trace the light field's scene "
            "again with the camera, every scattering sending its phase function's share to the image "
            "(exact for any g; with bands.polarization also Stokes Q and U)")
    include_stars: bool = param(
        True, type="bool", label="Include Stars", group=G_PICTURE,
        doc="Add each star's attenuated direct light to the pixel it falls in")
    exposure: Union[float, str] = param(
        "auto", type="\"auto\" or float", lo=0.0, lo_open=True, auto=True, number=1.0, group=G_PICTURE,
        doc="Factor applied to the linear colour before the sRGB curve; \"auto\": the one that maps the "
            "99th percentile of the scattered light's brightest colour component to full scale (the stars "
            "saturate)")


    vector_band: str = param(
        "", type="str", label="Band", group=G_VECTORS,
        doc="Nebula Polarization Vectors: the band whose vectors are drawn (empty: the image's first band)")
    vector_block: int = param(
        8, type="int", lo=1, hi=MAX_SKY_SIZE, unit="pixels", label="Block Size", group=G_VECTORS,
        doc="Nebula Polarization Vectors: one vector per block of this many pixels a side, from the "
            "block's summed I, Q and U")
    vector_scale: float = param(
        1.0, type="float", lo=0.0, lo_open=True, label="Vector Scale", group=G_VECTORS,
        doc="Nebula Polarization Vectors: a vector's length at P = 1, in blocks (its length is P times "
            "this times the block's side)")
    vector_snr: float = param(
        3.0, type="float", lo=0.0, label="Min Signal To Noise", group=G_VECTORS,
        doc="Nebula Polarization Vectors: a block's vector is drawn where its degree of polarization is "
            "at least this many of its standard errors")


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
