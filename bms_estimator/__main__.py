"""``python -m bms_estimator``: the ``bms-estimator`` command (where the console script is not on PATH)."""

import sys

from .cli.__main__ import main

if __name__ == "__main__":
    sys.exit(main())
