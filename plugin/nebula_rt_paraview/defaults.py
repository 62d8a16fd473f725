"""What Apply (or Show) shows, installed on import (by the plugin's entry file): the
true-colour volume with its stars (:mod:`.display`; only where this process has a client) and
the sky image in its own view's defaults (:mod:`.views`)."""

from . import display, views

views.install_view_defaults()
display.install()
