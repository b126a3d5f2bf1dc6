"""The DRVS server: camera registry and field-of-view routing."""

from drvs.server.server import DrvsServer

__all__ = ["DrvsServer"]
