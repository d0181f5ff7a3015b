"""The optional C fast paths (built by setup.py): present in CI, and each one's environment
variable turns it off. Each path's own tests compare it with its Python path."""

from __future__ import annotations

import importlib
import importlib.util
import os
import subprocess
import sys

import pytest

# (extension, module and flag that say whether it runs, variable that forces Python, extra condition)
EXTENSIONS = [
    ("protocol._fastcodec", "protocol.codec", "FAST_CODEC", "SUMOCO_PURE_CODEC", sys.byteorder == "little"),
    ("sumo_side._fastread", "sumo_side.simulation", "FAST_READ", "SUMOCO_PURE_READ", True),
    ("physics_side._pathkernel", "physics_side.reference", "FAST_PATHS", "SUMOCO_PURE_PHYSICS", True),
    ("physics_side._pathkernel", "physics_side.reference", "FAST_REFERENCE", "SUMOCO_PURE_PHYSICS", True),
    ("physics_side._pathkernel", "physics_side.reference", "FAST_PATHSET", "SUMOCO_PURE_PHYSICS", True),
    ("physics_side._worldkernel", "physics_side.world", "FAST_OBSERVE", "SUMOCO_PURE_PHYSICS", True),
    ("physics_side._controlkernel", "physics_side.control", "FAST_CONTROL", "SUMOCO_PURE_PHYSICS", True),
    ("physics_side.policies._policykernel", "physics_side.policies.carry", "FAST_TIGHTNESS", "SUMOCO_PURE_PHYSICS",
     True),
    ("physics_side.policies._footprintkernel", "physics_side.policies.footprints", "FAST_FOOTPRINTS",
     "SUMOCO_PURE_PHYSICS", True),
]
IDS = [e[0] for e in EXTENSIONS]


def _built(ext: str, usable: bool) -> bool:
    return importlib.util.find_spec(ext) is not None and usable


@pytest.mark.parametrize("ext, module, flag, env, usable", EXTENSIONS, ids=IDS)
def test_ci_builds_the_extension(ext, module, flag, env, usable):
    """CI installs with a compiler: losing an extension there must not go unnoticed (a CI
    job may still run the Python path on purpose, with the variable set)."""
    if not os.environ.get("CI"):
        pytest.skip("CI not set")
    assert _built(ext, usable), f"{ext} was not built"
    assert getattr(importlib.import_module(module), flag) is (os.environ.get(env, "") in ("", "0"))


@pytest.mark.parametrize("ext, module, flag, env, usable", EXTENSIONS, ids=IDS)
def test_the_variable_turns_the_fast_path_off(ext, module, flag, env, usable):
    code = f"from {module} import {flag}; print({flag})"
    environ = dict(os.environ, **{env: "1"})
    out = subprocess.run([sys.executable, "-c", code], env=environ, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    environ[env] = "0"
    out = subprocess.run([sys.executable, "-c", code], env=environ, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == str(_built(ext, usable))


def test_the_numpy_math_check_sees_a_difference(monkeypatch):
    """The physics kernels call libm; they stay off where numpy's own functions differ."""
    import numpy as np

    from runtime.native import numpy_math_is_libm

    assert numpy_math_is_libm()  # (on this build: the kernels' tests compare bit for bit)
    real = np.cos
    monkeypatch.setattr(np, "cos", lambda a: np.nextafter(real(a), np.inf))
    assert not numpy_math_is_libm()


def test_an_extension_from_another_directory_is_refused_and_logged(caplog):
    import logging
    from pathlib import Path
    from types import ModuleType

    import physics_side
    from runtime.native import beside_its_package

    here = ModuleType("physics_side._here")
    here.__file__ = str(Path(physics_side.__file__).parent / "_here.so")
    assert beside_its_package(here)
    there = ModuleType("physics_side._there")
    there.__file__ = "/elsewhere/checkout/physics_side/_there.so"
    with caplog.at_level(logging.WARNING, logger="runtime.native"):
        assert not beside_its_package(there)
    assert "physics_side._there" in caplog.text and "/elsewhere/checkout/physics_side" in caplog.text
    assert beside_its_package(ModuleType("physics_side._nofile"))  # (no file to compare: accepted)


def test_a_checkout_without_built_extensions_runs_its_python_paths(tmp_path):
    """A copy of the packages without the .so files: with this checkout installed editable, its
    extensions are on every package's search path; the copy must run its own Python paths,
    not this checkout's C (which may be another version)."""
    import shutil
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    for pkg in ("protocol", "runtime", "physics_side", "sumo_side"):
        shutil.copytree(root / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("*.so", "__pycache__"))
    flags = sorted({(module, flag) for _, module, flag, _, _ in EXTENSIONS})
    code = "import importlib; print(" + ", ".join(
        f"importlib.import_module({m!r}).{f}" for m, f in flags) + ", importlib.import_module('protocol').__file__)"
    env = {k: v for k, v in os.environ.items() if not k.startswith("SUMOCO_PURE")}
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    fields = out.stdout.split()
    assert fields[:-1] == ["False"] * len(flags), dict(zip(flags, fields))
    assert fields[-1].startswith(str(tmp_path)), out.stdout  # the copy's Python ran
