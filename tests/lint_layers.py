"""Check the layers of docs/architecture.md: the import-linter contracts of pyproject.toml, run on
the sources of a checkout as they are installed. From the repository root:

    .venv/bin/python tests/lint_layers.py [--root DIR] [lint-imports options, e.g. --verbose]

Exit status: lint-imports' own (0: every contract kept; 1: one broken, the import chain printed).
``--root``: the checkout to check (default: the one holding this file).

Why not plain ``lint-imports``: grimp (import-linter's import graph) finds a package's modules by
walking the folders of ``importlib.util.find_spec("rigctl").submodule_search_locations`` --
``['<repo>/rigctl']``. drivers/ and sim/ are installed as rigctl.drivers and rigctl.sim
(``package-dir`` in pyproject.toml); under the editable install (``pip install -e``) they exist
only in setuptools' editable finder, a ``sys.meta_path`` hook holding that mapping
(``__editable___rigctl_*_finder.MAPPING``), not as folders under rigctl/, so grimp never walks
them: "Missing layer in container 'rigctl': module rigctl.drivers does not exist". import-linter
has no setting for such a mapping. This builds a tree laid out as installed in a temporary
folder -- rigctl/* linked in, each package-dir mapping outside rigctl/ linked at its installed
place -- and runs the venv's lint-imports there with the checkout's pyproject.toml
(tests/test_layers.py runs the same, and plants violations to see each contract fail).
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def link_tree(dest: Path, planted: dict[str, str] | None = None, root: Path = ROOT) -> Path:
    """dest/rigctl as installed from checkout ``root``: rigctl/* linked, plus every package-dir
    mapping outside rigctl/ (rigctl.drivers -> drivers, rigctl.sim -> sim). ``planted``:
    {"sub/name.py": source} adds files (the sub-package's entries are then linked one by one);
    {"name.py": source} for a module of rigctl/ appends ``source`` to a copy of it."""
    pkg = dest / "rigctl"
    pkg.mkdir(parents=True)
    mapping = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    subs = {name.split(".", 1)[1]: root / src for name, src in mapping.items()
            if name.count(".") == 1 and Path(src).parts[0] != "rigctl"}
    assert {"drivers", "sim"} <= set(subs), mapping
    entries = {p.name: p for p in (root / "rigctl").iterdir() if p.name != "__pycache__"}
    entries.update(subs)
    planted = dict(planted or {})
    planted_dirs = {k.split("/")[0] for k in planted}
    for name, src in entries.items():
        if name in planted and src.is_file():
            (pkg / name).write_text(src.read_text() + "\n" + planted.pop(name))
        elif name in planted_dirs:
            (pkg / name).mkdir()
            for p in src.iterdir():
                rel = f"{name}/{p.name}"
                if rel in planted and p.is_file():  # a copy: never write through a link
                    (pkg / rel).write_text(p.read_text() + "\n" + planted.pop(rel))
                elif p.name != "__pycache__":
                    (pkg / name / p.name).symlink_to(p)
        else:
            (pkg / name).symlink_to(src)
    for rel, text in planted.items():
        (pkg / rel).write_text(text)
    return dest


def lint(tree: Path, args: list[str] | tuple[str, ...] = (), root: Path = ROOT,
         capture: bool = True) -> subprocess.CompletedProcess:
    """The venv's lint-imports on ``tree`` (:func:`link_tree`) with ``root``'s pyproject.toml;
    ``capture``: its output in the result, unwrapped (else on the console)."""
    exe = Path(sys.executable).parent / "lint-imports"
    if not exe.exists():
        raise SystemExit(f"{exe}: not found -- import-linter is part of the test extra: "
                         "pip install -e '.[test]'")
    env = dict(os.environ, PYTHONPATH=str(tree))
    if capture:
        env["COLUMNS"] = "400"  # no wrapped lines
    return subprocess.run([str(exe), "--no-cache", *args, str(root / "pyproject.toml")],
                          cwd=tree, env=env, capture_output=capture, text=True, timeout=300)


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    root = ROOT
    if "--root" in args:
        i = args.index("--root")
        if i + 1 >= len(args):
            raise SystemExit("--root needs a folder: the checkout whose layers to check")
        root = Path(args[i + 1]).absolute()
        del args[i:i + 2]
    if not (root / "pyproject.toml").is_file():
        raise SystemExit(f"{root}: no pyproject.toml -- run from the repository root, or pass --root")
    with tempfile.TemporaryDirectory(prefix="rigctl-layers-") as d:
        return lint(link_tree(Path(d), root=root), args, root=root, capture=False).returncode


if __name__ == "__main__":
    sys.exit(main())
