"""`rigctl validate` prints one table: the sample column and the time column start at the same
place on every step's line. Before, the rate steps' descriptions ('angles [0, 0, 0] deg, rate
+40 deg/s', 71 characters and more) overflowed their 70-character column, so in the quickstart's
first command the rate steps' columns stood one to two characters right of the others'."""
from __future__ import annotations

import contextlib
import io
import re

from helpers import ROOT

from rigctl import cli


def test_every_step_line_has_its_columns_in_the_same_place():
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = cli.main(["validate", str(ROOT / "procedures" / "full-calibration.yaml"),
                         "-p", "warmup=1 min", "-p", "sample=5 s"])
    assert code == 0
    rows = [line for line in out.getvalue().splitlines() if re.match(r"^\s*\d+  ", line)]
    assert len(rows) == 44 and any(" rate " in r for r in rows)  # warm-up, 24 orientations, 18 rates, solve
    starts = {re.search(r" (sample \S|after the run)", r).start() for r in rows}
    tildes = {r.index(" ~") for r in rows}
    assert len(starts) == 1 and len(tildes) == 1, (starts, tildes)
