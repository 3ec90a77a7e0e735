"""``python -m patexgs_jax.viewer``: the browser viewer's command line (:mod:`.server`)."""

import sys

from .server import main

if __name__ == "__main__":
    sys.exit(main())
