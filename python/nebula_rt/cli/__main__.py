"""``python -m nebula_rt.cli``: the ``nebula-rt`` command."""

import sys

from .commands import main

sys.exit(main())
