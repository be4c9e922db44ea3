"""The rig config's ``suspenders:`` section: read by rigctl.config.config, used by `rigctl run`,
`rigctl resume` (from the run's config snapshot) and `rigctl serve`; a bad value is refused
with its file and line. (The wired tests show the values at work over the wire: hold times of
2 s and 3 s, an IMU timeout of 20 s, a 1 MiB disk reserve.)"""
from __future__ import annotations

import io

import pytest
import yaml

from rigctl import cli
from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import RunOptions, resume_run, run_procedure
from rigctl.config.suspenders import SuspenderSettings
from rigctl.yamlio import InputError

from helpers import ROOT

BASE = (ROOT / "configs" / "sim.yaml").read_text()


def config_with(tmp_path, section: str, name: str = "rig.yaml"):
    p = tmp_path / name
    p.write_text(BASE + section)
    return p


def line_of(path, needle: str) -> int:
    return next(i for i, ln in enumerate(path.read_text().splitlines(), 1) if needle in ln)


def test_example_lab_config_documents_the_defaults():
    cfg = load_config(ROOT / "configs" / "example-lab.yaml")
    assert cfg.suspenders == SuspenderSettings()
    assert load_config(ROOT / "configs" / "sim.yaml").suspenders == SuspenderSettings()


def test_suspenders_section_is_read(tmp_path):
    p = config_with(tmp_path, "suspenders:\n  hold_s: 2 min\n  imu_timeout_s: 0.5\n  max_counter_gap: 3\n"
                              "  temperature_min_c: 10\n  temperature_max_c: 40.5\n  min_free_mib: 1.5\n")
    s = load_config(p).suspenders
    assert s == SuspenderSettings(hold_s=120.0, imu_timeout_s=0.5, max_counter_gap=3, temperature_min_c=10.0,
                                  temperature_max_c=40.5, min_free_bytes=int(1.5 * 2**20))


@pytest.mark.parametrize("section, needle, message", [
    ("suspenders:\n  hold_s: -1\n", "hold_s", "must be finite and not negative"),
    ("suspenders:\n  hold_s: soon\n", "hold_s", "cannot read 'soon' as a duration"),
    ("suspenders:\n  imu_timeout_s: 0\n", "imu_timeout_s", "must be longer than zero"),
    ("suspenders:\n  max_counter_gap: 1.5\n", "max_counter_gap", "must be a whole number"),
    ("suspenders:\n  temperature_min_c: 50\n  temperature_max_c: 20\n", "temperature_max_c",
     "temperature band [50, 20] degC is empty"),
    ("suspenders:\n  min_free_mib: lots\n", "min_free_mib", "must be a number"),
    ("suspenders:\n  hold: 5\n", "hold:", "unknown key 'hold' in 'suspenders'"),
    ("suspenders: 5\n", "suspenders:", "'suspenders' must be a mapping"),
])
def test_bad_value_names_file_and_line(tmp_path, section, needle, message):
    p = config_with(tmp_path, section)
    with pytest.raises(InputError) as exc:
        load_config(p)
    assert str(exc.value).startswith(f"{p}:{line_of(p, needle)}: ") and message in str(exc.value)


def test_run_and_serve_refuse_a_bad_section_naming_file_and_line(tmp_path, capsys):
    p = config_with(tmp_path, "suspenders:\n  temperature_max_c: hot\n")
    where = f"{p}:{line_of(p, 'temperature_max_c')}: "
    for argv in (["run", "procedures/warmup.yaml", "--config", str(p), "--out", str(tmp_path / "runs")],
                 ["serve", "--config", str(p), "--runs", str(tmp_path / "runs"),
                  "--socket", str(tmp_path / "s.sock")]):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"rigctl {argv[0]}: error: {where}'temperature_max_c' must be a number"), err
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_run_and_resume_use_the_configured_band(tmp_path):
    """A temperature band the emulated IMU is outside of: the run pauses on it, with the
    configured band in the message; resuming the run uses the band of its config snapshot."""
    p = config_with(tmp_path, "suspenders:\n  temperature_min_c: -40\n  temperature_max_c: 0\n")
    cfg = load_config(p)
    proc_path = tmp_path / "p.yaml"
    proc_path.write_text("procedure: band\nsteps:\n  - capture:\n      duration: 10 s\n")
    proc = load_procedure(proc_path, limits=cfg.limits)
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False,
                        options=RunOptions(max_pause_s=3.0))
    assert res.status == "failed" and "outside [-40, 0] degC" in res.message, res.message
    snapshot = yaml.safe_load((res.run_dir / "config.yaml").read_text())
    assert snapshot["suspenders"]["temperature_max_c"] == 0
    again = resume_run(res.run_dir, tmp_path / "runs", console=io.StringIO(), install_signals=False,
                       options=RunOptions(max_pause_s=3.0))
    assert again.status == "failed" and "outside [-40, 0] degC" in again.message
    ok = resume_run(res.run_dir, tmp_path / "runs", console=io.StringIO(), install_signals=False,
                    options=RunOptions(suspenders=SuspenderSettings(min_free_bytes=0)))  # given wins
    assert ok.status == "complete"
