"""Errors of the simulator."""


class SitlError(Exception):
    """Root of errors raised by the simulator."""


class MapError(SitlError):
    """A map file that cannot be used; the message names the file and the problem."""
