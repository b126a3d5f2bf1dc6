"""The DRVS server: camera registry and field-of-view routing."""

from drvs.server.config import ServerConfig
from drvs.server.server import DrvsServer

__all__ = ["DrvsServer", "ServerConfig"]
