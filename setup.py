"""The C fast paths: the wire codec's (protocol/_fastcodec.c), the SUMO side's vehicle read
(sumo_side/_fastread.c), the physics side's path evaluation (physics_side/_pathkernel.c), its
vehicles' observation and commands (physics_side/_worldkernel.c) and its per-step policies
(physics_side/policies/_policykernel.c, _footprintkernel.c); everything else is in pyproject.toml.

``optional=True``: without a compiler the install still succeeds and protocol.codec,
sumo_side.simulation and the physics side run their pure-Python paths.
"""

from setuptools import Extension, setup

# the physics kernels' shared rules of numpy's arithmetic (a change rebuilds all of them)
NUMPY_ARITH = ["physics_side/_numpy_arith.h"]

setup(ext_modules=[
    Extension("protocol._fastcodec", ["protocol/_fastcodec.c"], optional=True),
    Extension("sumo_side._fastread", ["sumo_side/_fastread.c"], optional=True),
    Extension("physics_side._pathkernel", ["physics_side/_pathkernel.c"], depends=NUMPY_ARITH, optional=True),
    Extension("physics_side._worldkernel", ["physics_side/_worldkernel.c"], depends=NUMPY_ARITH, optional=True),
    Extension("physics_side.policies._policykernel", ["physics_side/policies/_policykernel.c"], depends=NUMPY_ARITH, optional=True),
    Extension("physics_side.policies._footprintkernel", ["physics_side/policies/_footprintkernel.c"], depends=NUMPY_ARITH, optional=True),
])
