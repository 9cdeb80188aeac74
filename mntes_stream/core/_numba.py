"""numba when installed (else None), caching compiled kernels in the user's cache, not in the package.

numba caches next to the source by default: inside an installed package,
which must stay read-only and small, and which a reinstall throws away.
Here the cache goes to ``<cache_root>/numba`` (``mntes-stream cache``
shows, bounds and clears it) unless the user set ``NUMBA_CACHE_DIR``
(numba's own setting, then left as it is). numba keys each entry by the
source file's full path and time stamp, so two checkouts never share one.
"""

import os

from mntes_stream import cache_root

try:
    import numba
except ImportError:  # every kernel has a numpy twin
    numba = None

if numba is not None and not numba.config.CACHE_DIR:
    # Read when a function is decorated with cache=True: set before any kernel module decorates.
    numba.config.CACHE_DIR = os.path.join(cache_root(), "numba")
