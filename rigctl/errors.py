"""The one error hierarchy of rigctl, and the exit code each error means.

Every command (``rigctl run``, ``validate``, ``allan``, ``calibrate``, the daemon's verbs...)
raises one of these; the CLI entry point (:func:`rigctl.cli.main`) alone turns them into one line
on stderr and the exit code the README documents:

=====  ===========================================================================================
code   meaning
=====  ===========================================================================================
0      done
1      failure at run time: :class:`RunFailure` (a device that cannot be reached or stops
       answering: :class:`DeviceError`; a disk that cannot be written; a run that failed)
2      invalid input: :class:`InputError` (a procedure, config, recording or option that is
       wrong: the message names the file, and the line where there is one, and what to do)
130    interrupted (SIGINT / SIGTERM / ``rigctl abort``): :class:`Interrupted`
=====  ===========================================================================================

Any other exception is a bug: the entry point writes its traceback to the run log (a run) or to
the crash log (``rigctl.cli.crash_log_path``), prints one line saying where, and exits 1.
"""
from __future__ import annotations

from pathlib import Path

EXIT_OK, EXIT_FAILED, EXIT_INVALID, EXIT_INTERRUPTED = 0, 1, 2, 130


class RigctlError(Exception):
    """Base of every error rigctl reports to a user; ``exit_code`` is what the CLI exits with."""

    exit_code: int = EXIT_FAILED


class InputError(RigctlError):
    """Invalid user input (procedure, config, recording, option): carries file, line and a hint
    on what to do. Exit code 2."""

    exit_code = EXIT_INVALID

    def __init__(self, message: str, file: str | Path | None = None, line: int | None = None,
                 hint: str | None = None) -> None:
        self.message = message
        self.file = str(file) if file is not None else None
        self.line = line
        self.hint = hint
        super().__init__(str(self))

    def __str__(self) -> str:
        where = ""
        if self.file:
            where = f"{self.file}:{self.line}: " if self.line else f"{self.file}: "
        text = f"{where}{self.message}"
        if self.hint:
            text += f" ({self.hint})"
        return text


class InputErrors(InputError):
    """Several input errors found in one pass (one line each)."""

    def __init__(self, errors: list[InputError]) -> None:
        self.errors = list({str(e): e for e in errors}.values())  # one line per distinct error
        first = self.errors[0]
        super().__init__(first.message, first.file, first.line, first.hint)

    def __str__(self) -> str:
        return "\n".join(InputError.__str__(e) for e in self.errors)


class RunFailure(RigctlError):
    """A failure at run time (a run that failed, a settle timeout, a disk that cannot be
    written, an analysis that cannot complete on valid input). Exit code 1."""

    exit_code = EXIT_FAILED


class DeviceError(RunFailure):
    """A configured device cannot be opened, does not answer, or answers wrongly (checked before
    a run starts, ``rigctl validate --devices``; the drivers' own errors for a device that
    refuses or garbles a reply derive from it): one line per problem saying what is wrong and what
    to do. Takes one message or a list of them. Exit code 1.

    A driver's error for a setting of the rig config that the device cannot take (a rate, a baud
    rate, a configuration it refuses) derives from :class:`InputError` instead (exit code 2)."""

    def __init__(self, problems: list[str] | str) -> None:
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__("\n".join(self.problems))


class Interrupted(RigctlError):
    """Interrupted by SIGINT / SIGTERM / an operator's abort. Exit code 130."""

    exit_code = EXIT_INTERRUPTED
