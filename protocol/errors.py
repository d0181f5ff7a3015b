"""Error types shared by every sumoco package.

One base class, ``SumocoError``, so a daemon can catch everything of ours in one place;
each subclass names what was wrong and what was expected.
"""

from __future__ import annotations


class SumocoError(Exception):
    """Base of every error sumoco raises on purpose."""


class ProtocolError(SumocoError):
    """A message could not be decoded or failed validation.

    ``field`` names the offending field (dotted path, e.g. ``agents.x``) when known.
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        self.field = field
        super().__init__(f"{field}: {message}" if field else message)


class ConfigError(SumocoError):
    """A configuration file or value is missing or invalid (names the key or file)."""
