"""Exception types shared by the whole toolkit.

Every error caused by a user's input (a file, a parameter, a port) derives from
:class:`TofLocError`; the CLI turns it into a one-line message and exit code 2.
"""

from __future__ import annotations

from typing import Sequence


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


class UnknownParameterError(ParameterError):
    """A parameter name that an estimator, sensor model or other plug-in does not have.

    The message is one line: where the name was given (``--param KEY``, a config file's
    path and key; omitted when unknown), whose parameter it was meant to be, the closest
    valid name when one is close (:func:`difflib.get_close_matches`) and every valid name.

    Parameters
    ----------
    owner : str
        Whose parameter, e.g. ``"estimator 'beam_pf'"`` or ``"sensor model 'beam' of estimator 'beam_pf'"``.
    name : str
        The unknown name, as given.
    valid : sequence of str
        Every parameter ``owner`` has, in its own order.
    source : str, optional
        Where ``name`` was given (``"--param sensor_model__tempr"``, ``"run.toml: [estimator].n_particle"``).
    see : str, optional
        A command that describes the valid parameters (``"tofloc list --params beam_pf"``).
    """

    def __init__(self, owner: str, name: str, valid: Sequence[str], source: str | None = None, see: str = "") -> None:
        import difflib

        self.owner = owner
        self.name = name
        self.valid = list(valid)
        self.source = source
        close = difflib.get_close_matches(name, self.valid, n=1)
        self.suggestion: str | None = close[0] if close else None
        msg = f"{source}: " if source else ""
        msg += f"{owner} has no parameter {name!r}"
        if self.suggestion is not None:
            msg += f" (did you mean {self.suggestion!r}?)"
        msg += f"; its parameters: {', '.join(self.valid) if self.valid else 'none'}"
        if see:
            msg += f" (see `{see}`)"
        super().__init__(msg)


class PluginError(TofLocError, LookupError):
    """A plug-in is unknown or cannot be loaded."""


class PluginWarning(UserWarning):
    """A plug-in left out (a name another one already took, one that does not load): the
    CLI prints it as one ``warning:`` line, not as Python's warning with a source line."""
