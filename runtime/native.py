"""Optional C extensions of the hot paths, with their Python paths beside them.

Each C path is built by ``setup.py`` with ``optional=True``: without a compiler the install
still succeeds and the Python path runs. An environment variable forces the Python path
(tests compare the two; a suspected C bug can be ruled out without a rebuild).
"""

from __future__ import annotations

import importlib
import logging
import os
import sys
from types import ModuleType

log = logging.getLogger(__name__)


def optional_extension(module: str, pure_env: str) -> ModuleType | None:
    """The C extension ``module`` (dotted name); None when it is not built, when it was found
    in another checkout (``beside_its_package``), or when the environment variable
    ``pure_env`` is set to anything but "" or "0". (``protocol.codec`` loads its own: the
    protocol layer imports nothing of the runtime.)"""
    if os.environ.get(pure_env, "") not in ("", "0"):
        return None
    try:
        mod = importlib.import_module(module)
    except ImportError:
        return None
    return mod if beside_its_package(mod) else None


def beside_its_package(mod: ModuleType) -> bool:
    """Was the extension ``mod`` loaded from its own package's directory? An editable install
    adds the installed checkout to every package's search path, so a second checkout without
    built extensions silently ran its Python against the first one's C (whatever version
    that was). Such a module is refused (logged): the Python path runs until this checkout is
    built (``make``, or ``pip install -e .``)."""
    parent = sys.modules.get(mod.__name__.rpartition(".")[0])
    own, pkg = getattr(mod, "__file__", None), getattr(parent, "__file__", None)
    if own is None or pkg is None:
        return True
    here, there = os.path.dirname(os.path.realpath(own)), os.path.dirname(os.path.realpath(pkg))
    if here == there:
        return True
    log.warning("C extension %s found in %s, not beside its package in %s (another checkout's build): "
                "the Python path runs; build this checkout (make, or pip install -e .)", mod.__name__, here, there)
    return False


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


__all__ = ["beside_its_package", "numpy_math_is_libm", "optional_extension"]
