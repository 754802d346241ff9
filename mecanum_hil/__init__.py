"""mecanum-hil: hardware-in-the-loop bridge and data acquisition for Mecanum-wheeled robots."""

import os as _os

# The numerical work here is many tiny matrix operations (2x2 and 4x4 exponentials, small SVDs)
# beside numba's own threads: OpenBLAS threads only fight them for the cores (measured up to 10x
# slower on a 2-core machine). The user's own setting wins.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
