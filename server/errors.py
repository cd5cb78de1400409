"""The ground station's own exceptions; one handler maps them to HTTP."""


class SteelscanError(Exception):
    """Base of the ground station's errors."""


class NotFound(SteelscanError):
    """The thing asked for does not exist."""


class Conflict(SteelscanError):
    """The request clashes with what is stored."""


class IngestError(SteelscanError):
    """A robot message that is well-formed but cannot be stored (unknown session, ...);
    ``retry`` when it may be stored later (its session is not known yet)."""

    def __init__(self, message: str, *, retry: bool = False) -> None:
        super().__init__(message)
        self.retry = retry


class CommandError(SteelscanError):
    """Bad input to a command: printed as ``error: ...`` with exit status 2."""
