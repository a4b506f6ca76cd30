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


MAX_REPORTED = 20  # problems of one file reported at once; the rest are counted


class ProblemsError(ProblemError):
    """Several problems of one input, reported together so that one run shows them all.

    Behaves as its first problem (``reason``, ``field``); ``problems`` holds up to
    :data:`MAX_REPORTED` of them and ``total`` counts all. ``message`` has one line each.
    """

    def __init__(self, problems: list[ProblemError], total: int):
        self.problems = problems
        self.total = total
        first = problems[0]
        super().__init__(first.reason, source=first.source, field=first.field)

    @classmethod
    def of(cls, problems: list[ProblemError], total: int | None = None) -> ProblemError:
        """One error for ``problems`` (at least one): itself when there is just one.
        ``total``: how many were found, when only some of them were kept."""
        total = len(problems) if total is None else total
        if total == 1:
            return problems[0]
        return cls(problems[:MAX_REPORTED], total)

    @property
    def lines(self) -> list[str]:
        """One line per problem, and one counting those left out."""
        more = self.total - len(self.problems)
        tail = [f"… and {more} more problem{'s' * (more > 1)}"] if more > 0 else []
        return [problem.message for problem in self.problems] + tail

    @property
    def message(self) -> str:
        return "\n".join(self.lines)

    def located(self, source: str) -> ProblemError:
        for problem in self.problems:
            problem.located(source)
        return super().located(source)


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
