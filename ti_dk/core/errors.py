"""The errors ti_dk raises, in one place below every layer: each one a line that says what to change.

:class:`ConfigError` (bad input: exit status 2), :class:`OutputError` (output could not be written:
exit status 1), :class:`SimulationError` and :class:`Stopped` (the run went wrong, or a signal
stopped it); :class:`ExprError` and :class:`InitError` (a formula, an initial condition), which the
scene's loader turns into a :class:`ConfigError` naming the key.
"""


class ConfigError(ValueError):
    """Bad scene input; the message says what to change."""


class OutputError(RuntimeError):
    """Output could not be written (disk full, permission, quota): one line, exit status 1."""


class SimulationError(RuntimeError):
    """The run went wrong in a way the user can fix (unstable scheme, too many particles)."""


class Stopped(SimulationError):
    """SIGTERM, SIGINT or SIGHUP arrived: the run stopped between two steps, its output closed and
    marked incomplete. ``status``: the exit status a shell gives for that signal (143, 130, 129)."""

    def __init__(self, message: str, status: int):
        super().__init__(message)
        self.status = status  # 128 + the signal's number


class ExprError(ValueError):
    """A formula that is not allowed or does not fit the grid; the message says what to change."""


class InitError(ValueError):
    """An initial condition that cannot be made on this grid; the message says what to change."""
