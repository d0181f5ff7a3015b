"""sumoco: SUMO traffic driven in MuJoCo, over Eclipse Zenoh.

Sub-packages by layer (imports point down only, checked by ``lint-imports``):
``sumoco.app`` (commands) -> ``sumo_side`` / ``physics_side`` -> ``sumoco.testing``
(synthetic traffic) -> ``sumoco.common`` (config, sessions, logging, exit codes) ->
``protocol`` (the wire).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("sumoco")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
