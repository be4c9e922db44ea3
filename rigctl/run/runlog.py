"""A run's log: JSON lines in the run directory plus readable lines on the console."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import IO, Any

from ..clock import utc_now
from ..recording.shield import shielded


class RunLog:
    def __init__(self, path: Path | None, console: IO[str] | None = None) -> None:
        self._file = open(path, "a", encoding="utf-8") if path else None  # noqa: SIM115
        self.console = console if console is not None else sys.stdout
        self.t0 = time.monotonic()

    def __call__(self, kind: str, message: str, echo: bool = True, **fields: Any) -> None:
        """Append one JSON line; also print it on the console unless ``echo`` is False (lines
        the progress display already shows). Each line whole, also when an interruption arrives
        meanwhile (rigctl.recording.shield)."""
        with shielded():
            if self._file:
                rec = {"utc": utc_now(), "kind": kind, "message": message, **fields}
                self._file.write(json.dumps(rec) + "\n")
                self._file.flush()
            if not echo:
                return
            prefix = {"error": "error: ", "warning": "warning: ", "prompt": ">>> "}.get(kind, "")
            print(f"{prefix}{message}", file=self.console, flush=True)

    def close(self) -> None:
        if self._file:
            self._file.close()
            self._file = None
