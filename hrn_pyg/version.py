"""The package's version, read from the installed distribution's metadata (``setup.cfg``'s
``version`` is the one place it is written)."""

from __future__ import annotations

from importlib import metadata

#: the distribution's name on the package index
DISTRIBUTION = "hrn_pyg"


def package_version() -> str:
    """The installed version of :data:`DISTRIBUTION`; ``0+unknown`` when it is not installed
    (the package imported from a bare source tree)."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return "0+unknown"


__version__ = package_version()
