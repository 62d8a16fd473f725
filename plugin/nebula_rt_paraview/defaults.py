"""What the GUI does on its own, installed on import (by the plugin's entry file): what Apply
(or Show) shows, the true-colour volume with its stars (:mod:`.display`; only where this
process has a client) and the sky image in its own view's defaults (:mod:`.views`); and the
Abort button beside the progress bar, heard while a NebulaRT algorithm executes (:mod:`.abort`;
only in the GUI), also when it executes in a pvserver (:mod:`.remote_abort`, which opens the
server's side of that channel in a pvserver)."""

from . import abort, display, remote_abort, views

views.install_view_defaults()
display.install()
remote_abort.install(abort.install())
