"""One exception hierarchy for the service; the core's errors are part of it."""

from companion.core.errors import CoreError, GraphError, ScanError


class CompanionError(Exception):
    """Root of errors the service raises and reports (never a bare Exception)."""


class ConfigError(CompanionError):
    """A configuration file or value that cannot be used; the message names the key."""


__all__ = ["CompanionError", "ConfigError", "CoreError", "GraphError", "ScanError"]
