"""The C fast paths: the wire codec's (protocol/_fastcodec.c), the SUMO side's vehicle read
(sumo_side/_fastread.c), the physics side's path evaluation (physics_side/_pathkernel.c) and
its vehicle observation (physics_side/_worldkernel.c);
everything else is in pyproject.toml.

``optional=True``: without a compiler the install still succeeds and protocol.codec,
sumo_side.simulation, physics_side.reference and physics_side.world run their pure-Python paths.
"""

from setuptools import Extension, setup

setup(ext_modules=[
    Extension("protocol._fastcodec", ["protocol/_fastcodec.c"], optional=True),
    Extension("sumo_side._fastread", ["sumo_side/_fastread.c"], optional=True),
    Extension("physics_side._pathkernel", ["physics_side/_pathkernel.c"], optional=True),
    Extension("physics_side._worldkernel", ["physics_side/_worldkernel.c"], optional=True),
])
