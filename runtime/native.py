"""Optional C extensions of the hot paths, with their Python paths beside them.

Each C path is built by ``setup.py`` with ``optional=True``: without a compiler the install
still succeeds and the Python path runs. An environment variable forces the Python path
(tests compare the two; a suspected C bug can be ruled out without a rebuild).
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType


def optional_extension(module: str, pure_env: str) -> ModuleType | None:
    """The C extension ``module`` (dotted name); None when it is not built or the environment
    variable ``pure_env`` is set to anything but "" or "0". (``protocol.codec`` loads its own:
    the protocol layer imports nothing of the runtime.)"""
    if os.environ.get(pure_env, "") not in ("", "0"):
        return None
    try:
        return importlib.import_module(module)
    except ImportError:
        return None


__all__ = ["optional_extension"]
