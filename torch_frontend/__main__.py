"""``python -m torch_frontend``: the ``torch-frontend`` command line (what ``torchrun -m
torch_frontend ...`` runs on every rank)."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
