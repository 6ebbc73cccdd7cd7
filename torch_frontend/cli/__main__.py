"""``python -m torch_frontend.cli``: the ``torch-frontend`` command line."""

import sys

from . import main

if __name__ == "__main__":
    sys.exit(main())
