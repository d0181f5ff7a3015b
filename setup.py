"""The C fast paths: the wire codec's (protocol/_fastcodec.c), the SUMO side's vehicle read
(sumo_side/_fastread.c), the physics side's path evaluation (physics_side/_pathkernel.c), its
vehicles' observation and commands (physics_side/_worldkernel.c), the default controller
(physics_side/_controlkernel.c) and its per-step policies
(physics_side/policies/_policykernel.c, _footprintkernel.c); everything else is in pyproject.toml.

``optional=True``: without a compiler the install still succeeds and protocol.codec,
sumo_side.simulation and the physics side run their pure-Python paths.
"""

from setuptools import Extension, setup

# what every extension shares: buffers in, module definition (include/sumoco_capi.h)
CAPI = ["include/sumoco_capi.h"]
# the physics kernels' shared rules of numpy's arithmetic (a change rebuilds all of them)
NUMPY_ARITH = CAPI + ["physics_side/_numpy_arith.h"]


def fast_path(name: str, source: str, depends: list[str] = CAPI) -> Extension:
    return Extension(name, [source], include_dirs=["include"], depends=depends, optional=True)


setup(ext_modules=[
    fast_path("protocol._fastcodec", "protocol/_fastcodec.c"),
    fast_path("sumo_side._fastread", "sumo_side/_fastread.c"),
    fast_path("physics_side._pathkernel", "physics_side/_pathkernel.c", NUMPY_ARITH),
    fast_path("physics_side._worldkernel", "physics_side/_worldkernel.c", NUMPY_ARITH),
    fast_path("physics_side._controlkernel", "physics_side/_controlkernel.c", NUMPY_ARITH),
    fast_path("physics_side.policies._policykernel", "physics_side/policies/_policykernel.c", NUMPY_ARITH),
    fast_path("physics_side.policies._footprintkernel", "physics_side/policies/_footprintkernel.c", NUMPY_ARITH),
])
