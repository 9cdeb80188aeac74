"""Session-wide test set-up.

so3g (sotodlib's compiled core) and toast bundle shared libraries that must be
loaded before spt3g's: a process that imports ``spt3g.core`` first and then
``so3g`` or ``toast`` segfaults (spt3g 1.0.2, so3g 0.2.9, toast 3.0.6). The G3
and framework tests share one pytest process, so the frameworks go first.
"""

from __future__ import annotations

import contextlib
import importlib

for _name in ("so3g", "toast"):
    with contextlib.suppress(ImportError):
        importlib.import_module(_name)
