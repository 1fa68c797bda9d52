"""The exceptions this package raises on purpose; all derive from ``PlatoonOptError``.

Each message is one line that names what was wrong and the value found, so that the command
line can print it as it is. A ``ConfigurationError`` (a scenario file, an allocator option, a
command-line flag) is the caller's to fix: it ends a run wherever it is raised, and no fallback
swallows it (``PlatoonController.allocate``); an ``AllocationError`` is a step that failed.
"""

from __future__ import annotations


class PlatoonOptError(Exception):
    """Base of every error raised on purpose by platoon-opt."""


class ConfigurationError(PlatoonOptError, ValueError):
    """Input the caller must fix (a file, an option, a flag): never a step's failure, so never
    answered with a fallback."""


class ScenarioError(ConfigurationError):
    """A scenario file is malformed; the message is one line: file, key path, value."""


class OptionError(ConfigurationError):
    """An allocator option is unknown or has a wrong value; the message names the allocator, the
    option, what it must be and the value given (and, for an unknown option, the valid ones)."""


class AllocationError(PlatoonOptError, RuntimeError):
    """A step's allocation failed and the controller was asked not to fall back (``strict=True``):
    the allocator raised, or it answered with a fallback of its own (``Allocation.fell_back``).

    Attributes:
        allocator: the allocator's name.
        reason: what failed, one line (the exception's repr, or the fallback's status).
        t: simulated time of the step (s), or None.
        scenario, seed: the run, once known (``within``; the harness and the CLI add them).
    """

    def __init__(
        self,
        message: str = "",
        *,
        allocator: str = "",
        reason: str = "",
        t: float | None = None,
        scenario: str | None = None,
        seed: int | None = None,
    ) -> None:
        self.allocator, self.reason, self.t, self.scenario, self.seed = allocator, reason, t, scenario, seed
        if not message:
            where = [] if scenario is None else [f"on scenario {scenario}"]
            where += ([] if seed is None else [f"seed {seed}"]) + ([] if t is None else [f"at t = {t:.4g} s"])
            message = f"allocator {allocator} failed {', '.join(where)}: {reason}"
        super().__init__(" ".join(message.split()))  # one line

    def within(self, *, scenario: str, seed: int) -> AllocationError:
        """The same failure, naming the run it ended."""
        return AllocationError(
            allocator=self.allocator, reason=self.reason, t=self.t, scenario=scenario, seed=seed
        )


# Longest message a fallback status keeps (a solver's message can run to pages).
STATUS_MESSAGE = 200


def error_text(error: BaseException) -> str:
    """``"<Type>: <message>"`` on one line (the message cut at ``STATUS_MESSAGE`` characters),
    or ``"<Type>"`` for an exception without a message."""
    message = " ".join(str(error).split())
    if len(message) > STATUS_MESSAGE:
        message = message[: STATUS_MESSAGE - 3] + "..."
    return type(error).__name__ + (f": {message}" if message else "")
