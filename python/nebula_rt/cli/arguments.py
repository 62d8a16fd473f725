"""Argument types the commands' parsers share."""

from __future__ import annotations

import argparse


def file_name(text: str) -> str:
    """The value of an option that names a file: refused when empty. An empty value (``--png
    ""``, or an unset shell variable) read as the option not given, so an output asked for was
    silently left out, and ``compare --image ""`` compared the colours instead of the image."""
    if not text:
        raise argparse.ArgumentTypeError("needs a file name, not an empty value")
    return text
