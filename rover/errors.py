"""Exceptions of the library, and the exit statuses they stand for; only the CLI turns them into messages."""

from __future__ import annotations

from dataclasses import dataclass

EXIT_FAILED = 1
"""an operator failed, or an output could not be written (docs/exit-codes.md)"""
EXIT_BAD_INPUT = 2
EXIT_PARTIAL = 3
"""a host (or worker process) was lost: the outputs are partial"""


class RoverError(Exception):
    """Base of every error Rover raises on purpose."""


class BadInput(RoverError):
    """A user mistake: a bad file, name, endpoint or value. The CLI exits with status 2."""


@dataclass(frozen=True, order=True)
class Diagnostic:
    """One problem in a file, with its 1-based position (0 when unknown)."""

    file: str
    line: int
    col: int
    message: str

    def __str__(self) -> str:
        if self.line:
            return f"{self.file}:{self.line}:{self.col}: {self.message}"
        return f"{self.file}: {self.message}"


class SpecError(BadInput):
    """A pipeline or setup file with one or more problems, all collected before raising."""

    def __init__(self, diagnostics: list[Diagnostic]):
        self.diagnostics = sorted(diagnostics)
        super().__init__("\n".join(str(d) for d in self.diagnostics))


class TransportError(BadInput):
    """An endpoint that cannot be listened on or reached."""


class OperatorDefinitionError(RoverError):
    """An operator class whose declaration is inconsistent (a programming error, not user input)."""


class OperatorFailed(RoverError):
    """An operator's handler raised while processing a message."""


class OutputFailed(RoverError):
    """An output of a run could not be finished (a full disk, a folder that went away): the run failed."""


class PeerLost(RoverError):
    """Another host of a distributed run was lost before it was done: this host's outputs are
    finished and kept, but they cover only part of the run (run.json status `partial`)."""


class Interrupted(BaseException):
    """A command stopped by SIGINT or SIGTERM; the CLI exits 128 + signum after cleaning up."""

    def __init__(self, signum: int):
        self.signum = signum
        super().__init__(f"interrupted by signal {signum}")
