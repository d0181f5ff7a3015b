"""sumoco: SUMO traffic driven in MuJoCo, over Eclipse Zenoh.

The application layer, on top of ``sumo_side`` / ``physics_side`` -> ``synthetic``
(synthetic traffic) -> ``runtime`` (config, sessions, logging, exit codes) -> ``protocol``
(the wire); imports point down only, checked by ``lint-imports``. Grouped by concern:
``cli`` (the ``sumoco`` command), ``orchestrate`` (demo, router, certificates, map export),
``bench`` (every ``sumoco bench`` row), ``recording`` (MCAP record and replay), ``viewing``
(browser viewer, WebSocket gateway, Foxglove), ``analysis`` (summary, report, figures).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("sumoco")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
