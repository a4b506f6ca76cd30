"""Errors that carry enough context for a one-line message to the user.

Every problem with user input becomes a :class:`ProblemError` naming the source (file or
command-line option), the field inside it and the reason, so the CLI can print it and exit
with code 2 instead of a traceback.
"""

from __future__ import annotations


class MisdirectError(Exception):
    """Base class of every error this package raises on purpose."""


class ProblemError(MisdirectError, ValueError):
    """Invalid input: a model file, a scenario parameter or an alteration."""

    def __init__(self, reason: str, *, source: str | None = None, field: str | None = None):
        self.reason = reason
        self.source = source
        self.field = field
        super().__init__(self.message)

    @property
    def message(self) -> str:
        where = ": ".join(part for part in (self.source, self.field) if part)
        return f"{where}: {self.reason}" if where else self.reason

    def located(self, source: str) -> ProblemError:
        """The same error attributed to ``source`` when it did not know its file yet."""
        if self.source is None:
            self.source = source
            self.args = (self.message,)
        return self


class OptionError(ProblemError):
    """A solve option out of range or not taken by the method: names the library parameter
    (``time_limit``); the command line shows it as its flag (``--time-limit``)."""

    def __init__(self, reason: str, *, parameter: str):
        self.parameter = parameter
        super().__init__(reason, field=parameter)


class SolverError(MisdirectError, RuntimeError):
    """A solver could not produce an answer (missing backend, inconsistent result, ...)."""


class WriteError(MisdirectError):
    """An output could not be written (disk full, I/O error): nothing was reported as written."""
