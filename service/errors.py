"""The errors the service's callers (the HTTP API, the command line) catch.

:class:`InputError` is the project's one type for bad input (a field, a file, an argument),
defined in :mod:`sim.errors` and raised by every layer; it is re-exported here so that ``api``
depends on ``service`` only.
"""

from sim.errors import InputError

__all__ = ["InputError"]
