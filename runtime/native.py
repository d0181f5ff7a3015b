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


def numpy_math_is_libm() -> bool:
    """Do numpy's float64 cos, sin, tan, arctan2, arcsin and hypot give libm's bits (Python's
    ``math`` calls libm, as the C paths do)? Not on numpy builds with their own SIMD versions
    (some AVX-512 ones): a C path bit-identical to a numpy body then stays off."""
    import math

    import numpy as np

    x = np.concatenate([np.linspace(-7.0, 7.0, 301), np.random.default_rng(0).uniform(-1e4, 1e4, 200)])
    u = np.linspace(-1.0, 1.0, 101)
    pairs = ((np.cos, math.cos, x), (np.sin, math.sin, x), (np.tan, math.tan, x), (np.arcsin, math.asin, u))
    ok = all(np.array_equal(f(a), [g(v) for v in a.tolist()]) for f, g, a in pairs)
    y = x[::-1].copy()
    return ok and np.array_equal(np.arctan2(y, x), [math.atan2(p, q) for p, q in zip(y.tolist(), x.tolist())]) and \
        np.array_equal(np.hypot(y, x), [math.hypot(p, q) for p, q in zip(y.tolist(), x.tolist())])


__all__ = ["numpy_math_is_libm", "optional_extension"]
