"""``python -m fosmc_jax``: the ``fosmc`` command."""

import sys

from ._app.cli import main

sys.exit(main())
