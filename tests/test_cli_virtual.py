"""The command line, end to end, as a user runs it: the commands that keep no wall-clock
deadline (help, validate, bad input, a whole run on the emulator's virtual clock). They run on
any worker; tests/test_cli.py keeps the run read while it is written on a scaled clock
(REALTIME_FILES, tests/conftest.py)."""
import os
import subprocess
import sys

import h5py
import numpy as np

from helpers import ROOT, run_rigctl


def test_version_and_help():
    r = run_rigctl("--version")
    assert r.returncode == 0 and r.stdout.startswith("rigctl ")
    for sub in ([], ["run"], ["validate"]):
        r = run_rigctl(*sub, "--help")
        assert r.returncode == 0 and "usage: rigctl" in r.stdout


def test_every_subcommand_help_formats():
    """`rigctl COMMAND --help` for every command (in-process: argparse's own formatting). A
    help string with a bare '%' made `rigctl allan --help` an internal error."""
    import argparse

    from rigctl import cli

    sub = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert {"allan", "import", "calibrate"} <= set(sub.choices)
    for name, sp in sub.choices.items():
        assert sp.format_help().startswith("usage: rigctl " + name), name


def test_validate_full_calibration_prints_steps_total_and_volume():
    r = run_rigctl("validate", "procedures/full-calibration.yaml")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert sum("orientation" in line and "north" in line for line in lines) == 24
    assert sum(" rate " in line for line in lines) == 18
    assert any(line.startswith("total duration: about 3") for line in lines)  # ~33 min
    assert any(line.startswith("expected data volume:") and "MB" in line for line in lines)


def test_invalid_procedure_exits_2_naming_the_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("steps:\n  - warmup:\n      duration: 15 mn\n")
    r = run_rigctl("validate", str(bad))
    assert r.returncode == 2
    assert f"{bad}:3:" in r.stderr and "Traceback" not in r.stderr
    r = run_rigctl("run", str(bad), "--out", str(tmp_path))
    assert r.returncode == 2 and not any(tmp_path.glob("*-*/"))  # nothing ran, no run folder


def test_run_24pos_end_to_end_readable_with_bare_h5py(tmp_path):
    r = run_rigctl("run", "procedures/24pos.yaml", "--out", str(tmp_path), timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    lines = r.stdout.splitlines()
    assert "configs/sim.yaml" in lines[0] and "emulated" in lines[0]
    assert lines[-1].startswith("recording: ")
    # piped (not a terminal): progress as plain lines, one when each step starts and ends
    assert "\r" not in r.stdout and "\x1b" not in r.stdout
    assert sum(ln.startswith("[") and " started: " in ln for ln in lines) == 25
    assert any(ln.startswith("[25/25] done: orientation z north, phi 315 deg") for ln in lines), lines[-8:]
    assert any(ln.startswith("complete: 25/25 steps") and "dropped 0 samples" in ln for ln in lines)
    path = lines[-1].split("recording: ", 1)[1]
    run_dir = os.path.dirname(path)
    assert os.path.dirname(run_dir) == str(tmp_path) and run_dir.endswith("-24pos")
    assert os.path.exists(os.path.join(run_dir, "run.log.jsonl"))
    # Only what docs/data-format.md says:
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "rigctl-recording" and f.attrs["schema_version"] == 1
        assert f["run/status"][0] == b"complete"
        kinds = list(f["segments/kind"][()])
        assert kinds.count(b"warmup") == 1 and kinds.count(b"orientation") == 24 and len(kinds) == 25
        n = f["imu/time"].shape[0]
        rate = f["imu"].attrs["sample_rate_hz"]
        assert n >= (15 * 60 + 24 * 30) * rate
        assert np.all(np.diff(f["imu/counter"][()].astype(np.int64)) == 1)
        for group in ("imu", "table", "pulses", "segments", "events"):
            for name, ds in f[group].items():
                assert "units" in ds.attrs, f"{group}/{name} has no units"
        assert f["imu/specific_force"].attrs["units"] == "m/s^2"
        warm = int(np.flatnonzero(f["segments/kind"][()] == b"warmup")[0])
        assert f["segments/last_sample"][warm] - f["segments/first_sample"][warm] == 15 * 60 * rate
        assert f["meta"].attrs["ended_utc"] != ""
        assert "24-position" in f["meta"].attrs["procedure_text"]


def test_readme_commands_are_the_ci_commands():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    test_cmd = [line for line in ci.splitlines() if "pytest" in line and not line.startswith("#")]
    assert len(test_cmd) == 1 and test_cmd[0] in readme
    assert "rigctl run procedures/24pos.yaml" in readme.split("```")[1]


def test_command_map_matches_what_the_modules_register() -> None:
    import argparse

    from rigctl.cli import COMMANDS, build_parser
    full = build_parser()
    sub = next(a for a in full._actions if isinstance(a, argparse._SubParsersAction))
    assert set(sub.choices) == set(COMMANDS) | {"run", "validate"}
    for verb, module in COMMANDS.items():  # each module alone adds its own verbs
        only = build_parser([verb], everything=False)
        s = next(a for a in only._actions if isinstance(a, argparse._SubParsersAction))
        assert verb in s.choices, (verb, module)


def test_client_verbs_start_without_the_solvers() -> None:
    code = ("import sys; from rigctl.cli import build_parser; build_parser(['status', '--watch'], everything=False); "
            "print(sorted(m for m in ('scipy', 'matplotlib', 'rigctl.solvers.allan') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


def test_solver_commands_import_without_numba_or_scipy_stats() -> None:
    """numba (~0.25 s of CPU) is imported where a compiled kernel runs, not with the commands:
    a `rigctl calibrate`, `batch`, `report` or `allan` that runs no kernel does not pay for it
    (rigctl.solvers.allan_kernels imports allan_kernels_jit at first use); asking for HAVE_NUMBA
    then imports it: the kernels are still there. No command imports scipy.stats (~0.45 s):
    the solvers' distribution functions are rigctl.solvers.distributions (tap_match imports
    scipy.stats where it fits a line); nor does looking for tones, as every Allan fit does
    (allan_tones.welch_hann, not scipy.signal.welch, which imports scipy.stats)."""
    code = ("import sys\n"
            "from rigctl import cli\n"
            "for c in ('calibrate', 'allan', 'report', 'history', 'batch', 'sync', 'thermal', 'certificate',\n"
            "          'apply-cal', 'import'):\n"
            "    cli.build_parser([c], everything=False)\n"
            "import rigctl.run.runner, rigctl.service.daemon\n"
            "print('numba' in sys.modules, sorted(m for m in sys.modules if m.startswith('scipy.stats')))\n"
            "import numpy as np\n"
            "from rigctl.solvers import allan_tones\n"
            "y = np.random.default_rng(1).standard_normal(200_000)\n"
            "y += 0.05 * np.sin(2 * np.pi * 13.1 * np.arange(y.size) / 100.0)\n"
            "print(len(allan_tones.detect_tones(y, 100.0)['tones']),"
            " sorted(m for m in sys.modules if m.startswith(('scipy.signal', 'scipy.stats'))))\n"
            "from rigctl.solvers import allan_kernels as K\n"
            "print(K.HAVE_NUMBA, 'numba' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split("\n")[:3] == ["False []", "1 []", "True True"], r.stdout
