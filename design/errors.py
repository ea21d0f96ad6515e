"""Exceptions raised by :mod:`design`.

Every exception subclasses :class:`ValueError` (or :class:`TypeError`) so callers can
catch the broad class; the message names the field or argument that is wrong.
"""


#: Problems a ScenarioError's message lists (all are in ``problems``).
MAX_SHOWN_PROBLEMS = 50


class SocmonError(ValueError):
    """Base class of socmon's input and precondition errors."""


class ScenarioError(SocmonError):
    """A scenario (file, dict or arguments) is invalid.

    ``problems`` lists every violated invariant, each naming its field, so that a user
    fixes them all at once instead of one per run.
    """

    def __init__(self, problems, source=None):
        if isinstance(problems, str):
            problems = [problems]
        self.problems = list(problems)
        self.source = source
        where = f"{source}: " if source else ""
        if len(self.problems) == 1:
            msg = where + self.problems[0]
        else:
            shown = self.problems[:MAX_SHOWN_PROBLEMS]
            more = len(self.problems) - len(shown)
            msg = where + f"{len(self.problems)} problems:\n" + "\n".join(
                f"  - {p}" for p in shown
            ) + (f"\n  ... and {more} more" if more else "")
        super().__init__(msg)


class GainsError(SocmonError):
    """A gains file or gain array is invalid or does not fit the scenario."""


class NotObservableError(SocmonError):
    """The pair is not observable: some parent SCC holds no measured node.

    ``unmeasured`` lists the parent SCCs (as lists of node labels) that have no sensor.
    """

    def __init__(self, message, unmeasured=()):
        self.unmeasured = [list(c) for c in unmeasured]
        super().__init__(message)
