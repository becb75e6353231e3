"""Errors a user can act on: printed as one line, exit code 2, never a traceback."""

from __future__ import annotations

from pathlib import Path


class DrivesimError(Exception):
    """A problem with the user's input or workspace, reported as one readable line.

    :param message: what is wrong and what to do about it.
    :param path: the file or folder the problem is about, named at the start of the line.
    """

    exit_code = 2

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.message = message
        self.path = Path(path) if path is not None else None
        super().__init__(self.one_line())

    def one_line(self) -> str:
        """The message as the single line the CLI prints."""
        return f"{self.path}: {self.message}" if self.path is not None else self.message


class InputError(DrivesimError):
    """The input recording or file is unreadable, incomplete or unsupported."""


class ConfigError(DrivesimError):
    """A config file or `--set` override is invalid."""


class MissingArtifactError(DrivesimError):
    """A stage needs an artifact that the workspace does not have yet."""


class ArtifactConflictError(DrivesimError):
    """An artifact made with other settings would be replaced; the user must say so (--force) or pick a new name."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM stopped a command: not an error. The message says what was kept and how to continue.

    A KeyboardInterrupt, so every `except BaseException` cleanup (temporary folders, worker processes) runs as for a
    plain Ctrl-C.

    :param message: what was kept and the command that continues, e.g. "continue with `drivesim train --resume R`".
    """

    def __init__(self, message: str) -> None:
        self.message = message
        super().__init__(message)


class Terminated(KeyboardInterrupt):
    """SIGTERM (what `timeout`, Slurm and `docker stop` send), raised in the main thread and handled like Ctrl-C."""


class DiskFullError(DrivesimError):
    """The disk filled up while an artifact was written (errno ENOSPC); nothing half-written was kept."""

    exit_code = 1
