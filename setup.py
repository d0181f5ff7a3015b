"""The C fast paths: the wire codec's (protocol/_fastcodec.c) and the SUMO side's vehicle
read (sumo_side/_fastread.c); everything else is in pyproject.toml.

``optional=True``: without a compiler the install still succeeds and protocol.codec and
sumo_side.simulation run their pure-Python paths.
"""

from setuptools import Extension, setup

setup(ext_modules=[
    Extension("protocol._fastcodec", ["protocol/_fastcodec.c"], optional=True),
    Extension("sumo_side._fastread", ["sumo_side/_fastread.c"], optional=True),
])
