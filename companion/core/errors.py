"""The core's exceptions; the service's hierarchy (companion.errors) re-exports them."""


class CoreError(Exception):
    """Root of errors raised by the pure core."""


class ScanError(CoreError, ValueError):
    """A depth scan that cannot be turned into a polygon (malformed bearings, ranges, limits)."""


class GraphError(CoreError, KeyError):
    """A pose-graph query about a keyframe that does not exist or is not connected."""
