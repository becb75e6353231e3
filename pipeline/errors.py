"""Errors a user can act on: printed as one line, exit code 2, never a traceback."""

from __future__ import annotations

from pathlib import Path


def printable(text: str) -> str:
    """`text` with every character that is not printable (newline, carriage return, tab, escape sequences, Unicode
    line separators, undecodable bytes of a file name) written as its Python escape (`\\n`, `\\x1b`, `\\udcff`), so
    a file name cannot forge a second line or recolour the terminal."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape", "backslashreplace").decode() for c in text)


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
        """The message as the single line the CLI prints (control characters in it escaped)."""
        return printable(f"{self.path}: {self.message}" if self.path is not None else self.message)


class InputError(DrivesimError):
    """The input recording or file is unreadable, incomplete or unsupported."""


class ConfigError(DrivesimError):
    """A config file or `--set` override is invalid."""


class MissingArtifactError(DrivesimError):
    """A stage needs an artifact that the workspace does not have yet."""


class StaleArtifactError(MissingArtifactError):
    """A stage needs an artifact whose files changed since it was written, or whose upstream artifact was rebuilt
    since: the message names the commands that refresh it."""


class ArtifactBusyError(DrivesimError):
    """Another process is writing the same artifact of the workspace (it holds the artifact's lock)."""


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
    """SIGTERM (what `timeout`, Slurm and `docker stop` send) or SIGHUP (a closed terminal or ssh session), raised in
    the main thread and handled like Ctrl-C.

    :param signum: the signal that stopped the command.
    """

    def __init__(self, signum: int = 15) -> None:
        self.signum = signum
        super().__init__()


class DiskFullError(DrivesimError):
    """The disk filled up while an artifact was written (errno ENOSPC); nothing half-written was kept."""

    exit_code = 1
