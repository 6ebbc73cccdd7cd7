"""The ``torchrun`` entry of ``tests/test_elastic.py``: ``torch-frontend`` with the checkpoint test
hook (``TORCH_FRONTEND_TEST_KILL_AT``) armed on one rank, at the job's first start only.

``TF_TEST_KILL_RANK`` names the rank and ``TF_TEST_KILL_AT`` the hook's value; the hook is set
only when ``TORCHELASTIC_RESTART_COUNT`` is 0, so the restarted worker group runs to the end.
(A script, not a test module: torchrun starts it as every rank's program.)"""

import os
import sys

if (os.environ.get("TORCHELASTIC_RESTART_COUNT", "0") == "0"
        and os.environ.get("RANK") == os.environ.get("TF_TEST_KILL_RANK")):
    os.environ["TORCH_FRONTEND_TEST_KILL_AT"] = os.environ["TF_TEST_KILL_AT"]

from torch_frontend.cli import main  # noqa: E402

sys.exit(main(sys.argv[1:]))
