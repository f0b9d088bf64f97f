"""companion: autonomous exploration on a multirotor's companion computer."""

__version__ = "0.1.0"
