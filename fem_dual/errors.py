"""The two ways a run can end badly, each with its exit status."""

__all__ = ["InputError", "SolveError", "one_line"]


class InputError(ValueError):
    """Bad input from the user: one line names the bad value; exit status 2."""

    exit_status = 2


class SolveError(RuntimeError):
    """A solve that failed (divergence, singular DtP map, blow-up); exit status 3.

    Attributes:
        slab: index of the slab that failed (0-based), if known.
        partial: the result of the slabs completed before the failure, if any.
    """

    exit_status = 3

    def __init__(self, message: str, slab: "int | None" = None):
        super().__init__(message)
        self.slab = slab
        self.partial = None


def one_line(exc: BaseException) -> str:
    """An exception as one line of a message: its type and its text with white space folded (an
    OSError's text alone: it names the file and the cause)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if not isinstance(exc, OSError) else text
