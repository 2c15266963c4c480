"""``python -m benchmarks``: run every benchmark script (see :mod:`benchmarks.run_all`)."""

import sys

from benchmarks.run_all import main

sys.exit(main())
