"""srvwire's version, read once from the installed package's metadata.

It lives in the bottom layer so that every module (the server's discovery document, the command
line, the package's ``__init__``) reports the same value from one place.
"""

from __future__ import annotations

from importlib import metadata

__all__ = ["__version__"]

try:
    __version__ = metadata.version("srvwire")
except metadata.PackageNotFoundError:  # pragma: no cover - a source tree that is not installed
    __version__ = "0+unknown"
