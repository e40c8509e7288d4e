"""Exception types shared by the whole toolkit.

Every error caused by a user's input (a file, a parameter, a port) derives from
:class:`TofLocError`; the CLI turns it into a one-line message and exit code 2.
"""

from __future__ import annotations


class TofLocError(Exception):
    """Base class of every error raised on bad user input."""


class FormatError(TofLocError, ValueError):
    """A file breaks its format: names the file, the path inside it and the expectation."""

    def __init__(self, file: object, where: str, expected: str, found: object | None = None) -> None:
        self.file = str(file)
        self.where = where
        self.expected = expected
        self.found = found
        msg = f"{self.file}: {where}: expected {expected}"
        if found is not None:
            msg += f", found {found}"
        super().__init__(msg)


class ParameterError(TofLocError, ValueError):
    """A parameter (of an estimator, a sensor model, a scenario, ...) is out of its domain."""


class PluginError(TofLocError, LookupError):
    """A plug-in is unknown or cannot be loaded."""
