"""`rigctl batch` and `rigctl serve --http` on a machine without their extras (Dask; starlette and
uvicorn). `rigctl batch` without the batch extra: one line saying what to install,
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


def test_serve_http_without_the_web_extra_says_what_to_install(tmp_path, monkeypatch):
    """`rigctl serve --http` without starlette and uvicorn: one line naming the extra, exit 2,
    before the daemon takes its runs directory or socket; before, 'internal error:
    ModuleNotFoundError: No module named 'starlette'', exit 1, after both were taken."""
    for name in ("starlette", "uvicorn"):
        monkeypatch.setitem(sys.modules, name, None)
    runs, sock = tmp_path / "runs", tmp_path / "s" / "rigctl.sock"
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(["serve", "--http", "127.0.0.1:0", "--runs", str(runs), "--socket", str(sock)])
    lines = err.getvalue().strip().splitlines()
    assert code == 2, err.getvalue()
    assert len(lines) == 1 and "starlette" in lines[0] and "pip install -e '.[web]'" in lines[0], lines
    assert not runs.exists() and not sock.exists()
