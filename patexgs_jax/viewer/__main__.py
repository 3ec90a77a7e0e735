"""``python -m patexgs_jax.viewer``: the browser viewer's command line (:mod:`.server`)."""

import sys

from .server import main

sys.exit(main())
