"""What `rigctl allan` says on the console while and after it works: the stream's progress
with windows left out (`drop`: excursions, a quiet stretch) counts the rows read, so it ends at
100 % with no negative time left (it went to 113 % with "left ~-0.0143 s" on the ADIS16405's
quiet stretch: the total was the rows summed, the count the rows reached); the fits' own
progress; the per-axis summary line's coverage."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from recording_helpers import write_recording
from rigctl.analysis import allan as AA


class Seen(AA.WorkProgress):
    """The real progress display, and every (done, total) it was given (the stream's; the
    fits' in ``fits``)."""
    updates: list[tuple[float, float]] = []
    fits: list[tuple[float, float]] = []

    def update(self, done: float) -> None:
        super().update(done)
        (Seen.fits if self.label.endswith(", fits") else Seen.updates).append((self.done, self.total))


def test_progress_with_windows_left_out_stays_within_the_rows(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(AA, "CHUNK_ROWS", 8192)
    n = 60_000
    rng = np.random.default_rng(3)
    g = np.column_stack([rng.standard_normal(n) * 1e-3, np.full(n, 1e-3), np.full(n, -1e-3)])
    rec = write_recording(tmp_path / "r.h5", 100.0, angular_rate=g)
    drop = [(10_000, 20_000)]
    monkeypatch.setattr(AA, "WorkProgress", Seen)
    Seen.updates = []
    out = io.StringIO()
    AA.compute_once(str(rec), ["gx"], 40, True, progress_stream=out, drop=drop)
    assert len(Seen.updates) >= 3  # one per chunk
    assert Seen.updates[-1] == (n, n)  # ends at 100 %: the rows read, the window included
    assert all(done <= total for done, total in Seen.updates)
    assert "allan r.h5, 1 axis: 60,000 samples in" in out.getvalue()


def test_the_fits_have_progress_of_their_own(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """After the stream, the axes' fits (silent for ~40 s on the 2.8 h ADIS16405 record) show
    their progress: one step per axis, and a closing line."""
    rng = np.random.default_rng(4)
    n = 20_000
    rec = write_recording(tmp_path / "r.h5", 100.0, angular_rate=rng.standard_normal((n, 3)) * 1e-3)
    monkeypatch.setattr(AA, "WorkProgress", Seen)
    Seen.fits = []
    out = io.StringIO()
    AA.compute_once(str(rec), ["gx", "gy", "gz"], 40, True, progress_stream=out)
    assert Seen.fits == [(1, 3), (2, 3), (3, 3)]
    assert "allan r.h5, fits: 3 axes in" in out.getvalue(), out.getvalue()


def test_the_summary_line_says_its_coverage(tmp_path: Path) -> None:
    """The per-axis line a run's analysis prints ('allan gz: N 0.1996 deg/sqrt(h) [0.198,
    0.2013]; B ...; K < 134 ...') said neither what the brackets hold nor what the bounds are."""
    rng = np.random.default_rng(5)
    rec = write_recording(tmp_path / "r.h5", 100.0, angular_rate=rng.standard_normal((20_000, 3)) * 1e-3)
    r = AA.compute_once(str(rec), ["gx"], 40, True)["axes"]["gx"]
    line = AA.summary_line(r)
    assert line.startswith("N ") and "[" in line and "K < " in line, line
    assert line.endswith(" (95 % intervals and upper bounds)"), line
