"""``python -m benchmarks.cambada``: see :mod:`benchmarks.cambada.run`."""

import sys

from .run import main

sys.exit(main())
