"""Moved to dragd/server.py (#32: the JSON-lines server beside protocol.py). Re-exported here only until daemon/core.py
and daemon/commands.py import it from there; delete this file then."""

from dragd.server import CommandTable, ControlServer

__all__ = ["CommandTable", "ControlServer"]
