"""`rigctl batch` on a machine without the batch extra (Dask): one line saying what to install,
exit 2, before anything is printed or analysed -- the first thing a user who installed only
`pip install -e .` meets. Before, it printed its 'N recordings on Dask local scheduler' line, then
'internal error: ModuleNotFoundError: No module named 'dask'', exit 1."""
from __future__ import annotations

import contextlib
import io
import sys

from rigctl import cli


def test_batch_without_dask_says_what_to_install(tmp_path, monkeypatch):
    for name in ("dask", "distributed"):  # not installed, as after `pip install -e .`
        monkeypatch.setitem(sys.modules, name, None)
    run = tmp_path / "runs" / "20260101T000000Z-24pos"
    run.mkdir(parents=True)
    (run / "recording.h5").write_bytes(b"")  # the glob must match something
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(["batch", str(tmp_path / "runs" / "*" / "recording.h5"), "--db", "none"])
    lines = err.getvalue().strip().splitlines()
    assert code == 2, err.getvalue()
    assert len(lines) == 1 and "dask" in lines[0] and "pip install -e '.[batch]'" in lines[0], lines
    assert "internal error" not in err.getvalue()
    assert out.getvalue() == ""  # nothing announced that will not happen
