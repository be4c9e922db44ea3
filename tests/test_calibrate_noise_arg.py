"""`rigctl calibrate --noise` given something that is not a recording file: one line saying what
it is and what to give, before any analysis (the new-user audit: a directory got 'no such file')."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from recording_helpers import write_recording
from rigctl.cli import main


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    rng = np.random.default_rng(5)
    return write_recording(tmp_path / "recording.h5", 100.0, angular_rate=1e-3 * rng.standard_normal((2000, 3)),
                           specific_force=1e-3 * rng.standard_normal((2000, 3)))


@pytest.mark.parametrize("command", ["calibrate", "batch"])
def test_noise_directory_says_it_is_a_directory(recording: Path, tmp_path: Path, capfd, command) -> None:
    night = tmp_path / "overnight-run"
    night.mkdir()
    assert main([command, str(recording), "--noise", str(night), "--db", "none"]) == 2
    out, err = capfd.readouterr()
    lines = err.strip().splitlines()
    assert out == "" and len(lines) == 1, (out, err)  # the error first: no progress line before it
    assert f"--noise {night}: is a directory, not a recording" in lines[0], lines[0]
    assert str(night / "recording.h5") in lines[0] and "no such file" not in lines[0], lines[0]


def test_noise_missing_file_still_says_no_such_file(recording: Path, tmp_path: Path, capfd) -> None:
    assert main(["calibrate", str(recording), "--noise", str(tmp_path / "nope.h5")]) == 2
    err = capfd.readouterr().err.strip()
    assert "nope.h5: no such file" in err and "\n" not in err, err


@pytest.mark.parametrize("command,opt", [("calibrate", "--json"), ("thermal", "--json"), ("thermal", "--csv")])
def test_an_output_file_that_cannot_be_written_is_refused_first(recording: Path, tmp_path: Path, capfd,
                                                                command, opt) -> None:
    """`rigctl calibrate REC --json /no/such/dir/x.json` analysed (and stored its results) and only
    then failed with '[Errno 2] No such file or directory: '/no/such/dir/.x.json.tmp'', exit 1;
    now one line before any work, exit 2 (as rigctl allan's --json, --csv, --plot, --kalibr)."""
    target = tmp_path / "no-such-dir" / "x.out"
    assert main([command, str(recording), opt, str(target)] + (["--db", "none"] if command == "calibrate" else [])) == 2
    out, err = capfd.readouterr()
    lines = err.strip().splitlines()
    assert out == "" and len(lines) == 1, (out, err)
    assert f"{target.parent}: {opt}: output directory does not exist" in lines[0], lines[0]
