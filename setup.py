"""The C fast path of the wire codec (protocol/_fastcodec.c); everything else is in pyproject.toml.

``optional=True``: without a compiler the install still succeeds and protocol.codec runs
its pure-Python path.
"""

from setuptools import Extension, setup

setup(ext_modules=[
    Extension("protocol._fastcodec", ["protocol/_fastcodec.c"], optional=True),
    Extension("physics_side._pathkernel", ["physics_side/_pathkernel.c"], optional=True),
])
