"""Run benchmarks at two commits back to back and print the ratio of their headline figures.

    .venv/bin/python benchmarks/compare.py OLD NEW [--bench sync,decode,e2e] [--args 'decode=200000']

For each benchmark, the OLD commit's script then the NEW commit's script run one right after the
other (same machine load as far as that goes), each on its own commit's code: every commit is
checked out with ``git worktree add --detach`` in a temporary folder, laid out as installed
(each ``package-dir`` mapping of its pyproject.toml linked into its rigctl/: drivers/ as
rigctl.drivers, sim/ as rigctl.sim) and put first on PYTHONPATH, so the venv's editable install
of the current checkout is not what runs, in the benchmark or in its child processes. The
interpreter (and so the dependencies) is this one.

Every benchmark prints one JSON object as its last line (units in the keys). For each numeric
key the two have in common: old, new, new/old, and which way is better when the key's name
says (a time, error, memory or size: lower; a rate, ``per_s``, speed-up: higher; otherwise
"?"). Exit status 0; the verdict is the reader's, with the machine's load (printed at the
start and end: other work on the machine moves wall-clock figures, CPU figures less).

``--repeats N`` runs each benchmark N times at each commit, alternating which goes first, and
compares the means. ``--args NAME=ARGS`` passes arguments to one benchmark (repeatable; shell-split), e.g. to run a
long benchmark on less work at both commits alike.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
UNITS_LOWER = {"s", "ms", "us", "ns", "h", "ppm", "ppb", "mb", "mib", "gb", "gib", "bytes", "rss"}
COUNT_HIGHER = {"frames", "msgs", "messages", "samples", "requests", "rows", "taps", "runs"}


def direction(key: str) -> str:
    """Which way is better, from the key's name: "lower" for a time, error or size (unit last,
    or ``S_per_X`` with a time or size S), "higher" for a rate (``frames_per_s``), a speed-up or
    a ratio of simulated to wall time; "?" otherwise."""
    tok = key.lower().replace(".", "_").split("_")
    if "per" in tok:
        i = tok.index("per")
        num = tok[i - 1] if i else ""
        if num in UNITS_LOWER:
            return "lower"
        per_time = tok[i + 1:i + 2] == ["s"] or tok[i + 1:i + 3] == ["cpu", "s"]
        return "higher" if num in COUNT_HIGHER or per_time else "?"
    if "speedup" in tok or ("ratio" in tok and "wall" in tok):
        return "higher"
    if tok[-1] in UNITS_LOWER or any(w in tok for w in ("err", "error", "errors", "false")):
        return "lower"
    return "?"


def checkout(commit: str, where: Path) -> Path:
    """A detached worktree of ``commit`` whose rigctl/ also holds its ``package-dir`` mappings
    (drivers/ as rigctl/drivers, sim/ as rigctl/sim, symbolic links), so that ``import rigctl``
    from that folder -- on PYTHONPATH, or as the current directory of a ``python -c`` or
    ``python -m`` child -- is that commit's code throughout, and the venv's editable install of
    another checkout is never reached for a sub-package."""
    wt = where / f"wt-{commit[:10]}"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(wt), commit], check=True)
    cfg = tomllib.loads((wt / "pyproject.toml").read_text())
    mapping = cfg.get("tool", {}).get("setuptools", {}).get("package-dir", {})
    for name, src in mapping.items():
        parts = name.split(".")
        if len(parts) == 2 and Path(src).parts[0] != "rigctl" and not (wt / "rigctl" / parts[1]).exists():
            (wt / "rigctl" / parts[1]).symlink_to(wt / src)
    return wt


def run(wt: Path, bench: str, args: list[str], timeout: float) -> tuple[dict, float, str]:
    env = dict(os.environ, PYTHONPATH=str(wt), PYTHONDONTWRITEBYTECODE="1")
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, str(wt / "benchmarks" / f"{bench}.py"), *args], cwd=wt, env=env,
                       capture_output=True, text=True, timeout=timeout)
    wall = time.monotonic() - t0
    lines = [ln for ln in p.stdout.strip().splitlines() if ln.strip()]
    try:
        out = json.loads(lines[-1]) if p.returncode == 0 and lines else {}
    except json.JSONDecodeError:
        out = {}
    why = "" if out else f"exit {p.returncode}: {(p.stderr or p.stdout).strip().splitlines()[-1:]}"
    return out, wall, why


def mean_of(results: list[tuple[dict, float, str]]) -> tuple[dict, float, str]:
    """The mean of each numeric figure over repeated runs (the first error, if any)."""
    why = next((w for _, _, w in results if w), "")
    if why:
        return {}, 0.0, why
    figs = [flat(r) for r, _, _ in results]
    keys = set.intersection(*(set(f) for f in figs))
    return ({k: sum(f[k] for f in figs) / len(figs) for k in keys},
            sum(w for _, w, _ in results) / len(results), "")


def flat(d: dict, prefix: str = "") -> dict[str, float]:
    out: dict[str, float] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flat(v, f"{prefix}{k}."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[prefix + k] = float(v)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old")
    ap.add_argument("new")
    ap.add_argument("--bench", default=",".join(sorted(p.stem for p in (ROOT / "benchmarks").glob("*.py")
                                                      if p.stem != "compare")))
    ap.add_argument("--args", action="append", default=[], metavar="NAME=ARGS")
    ap.add_argument("--timeout", type=float, default=3600.0, help="per benchmark run, s")
    ap.add_argument("--repeats", type=int, default=1,
                    help="runs of each benchmark at each commit, the order alternating (old new, new old, "
                         "...); figures are the means")
    a = ap.parse_args()
    extra = {k: shlex.split(v) for k, v in (x.split("=", 1) for x in a.args)}
    commits = [subprocess.run(["git", "-C", str(ROOT), "rev-parse", c], capture_output=True, text=True,
                              check=True).stdout.strip() for c in (a.old, a.new)]
    print(f"old {commits[0][:10]}  new {commits[1][:10]}  load average {os.getloadavg()[0]:.2f} "
          f"on {os.cpu_count()} CPUs", flush=True)
    summary: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="rigctl-compare-") as tmp:
        wts = [checkout(c, Path(tmp)) for c in commits]
        try:
            for bench in a.bench.split(","):
                runs: list[list[tuple[dict, float, str]]] = [[], []]
                for r in range(a.repeats):  # old, new; then new, old; ...
                    for i in ((0, 1) if r % 2 == 0 else (1, 0)):
                        wt = wts[i]
                        if not (wt / "benchmarks" / f"{bench}.py").exists():
                            runs[i].append(({}, 0.0, "no such benchmark at this commit"))
                        else:
                            runs[i].append(run(wt, bench, extra.get(bench, []), a.timeout))
                (old, w0, why0), (new, w1, why1) = (mean_of(x) for x in runs)
                print(f"\n== {bench} (wall {w0:.0f} s old, {w1:.0f} s new)", flush=True)
                if why0 or why1:
                    print(f"   not compared: old {why0 or 'ok'}; new {why1 or 'ok'}")
                    summary[bench] = {"error": why0 or why1}
                    continue
                fo, fn = old, new
                rows = {}
                for k in sorted(set(fo) & set(fn)):
                    ratio = fn[k] / fo[k] if fo[k] else (1.0 if fn[k] == fo[k] else float("inf"))
                    d = direction(k)
                    worse = (d == "lower" and ratio > 1) or (d == "higher" and ratio < 1)
                    rows[k] = round(ratio, 4) if math.isfinite(ratio) else None
                    print(f"   {k:55s} {fo[k]:>14.6g} {fn[k]:>14.6g}  x{ratio:8.4f}  better {d:6s}"
                          f"{'  (worse)' if worse else ''}")
                only = sorted(set(fo) ^ set(fn))
                if only:
                    print(f"   in one only: {', '.join(only)}")
                summary[bench] = rows
        finally:
            for wt in wts:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(wt)], check=False)
    print(f"\nload average at the end {os.getloadavg()[0]:.2f}")
    print(json.dumps({"old": commits[0], "new": commits[1], "ratio_new_over_old": summary}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
