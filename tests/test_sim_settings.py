"""The emulator's config sections (``table.sim``, ``imu.sim`` with ``thermal`` and Gauss-Markov
terms, ``pulses.sim``, ``chamber.sim``) on the typed settings of rigctl/settings.py: each
malformed section is one InputError with the file, the line and what to do, word for word."""
from __future__ import annotations

from pathlib import Path

import pytest

from rigctl.config.config import load_config
from rigctl.engine.rig import open_rig
from rigctl.yamlio import InputError

TEMPLATE = """rig: t
seed: 1
table:
  driver: sim
  sim:
    damping: 0.6
imu:
  driver: sim
  rate_hz: 100
  sim:
    gyro_arw_deg_rth: 0.2
pulses:
  driver: sim
  sim:
    axis: z
chamber:
  driver: sim
  sim:
    air_damping: 0.6
"""
TABLE, IMU, PULSES, CHAMBER = ("    damping: 0.6\n", "    gyro_arw_deg_rth: 0.2\n", "    axis: z\n",
                               "    air_damping: 0.6\n")

# (line of the template replaced, its replacement, the error: 'LINE: message (hint)')
CASES = {
    "chamber typo": (CHAMBER, "    air_dampin: 0.6\n",
                     "19: unknown key 'air_dampin' in 'chamber.sim' (did you mean 'air_damping'?)"),
    "chamber maximum": (CHAMBER, CHAMBER + "    initial_c: 300\n",
                        "20: 'initial_c' = 300 is above its maximum 200"),
    "chamber between fields": (CHAMBER, CHAMBER + "    initial_c: 60\n    max_c: 50\n",
                               "20: 'initial_c' 60 degC must lie inside [min_c, max_c] = [-70, 50] degC"),
    "tap sign": (PULSES, PULSES + "    sign: 0.5\n",
                 "16: 'sign' must be -1 or +1, got 0.5 (it is the direction of the blow along 'axis'; "
                 "the size of the blow is 'amplitude_median_m_s2')"),
    "tap axis": (PULSES, "    axis: w\n", "15: 'axis' = 'w' is not allowed (choose one of: x, y, z)"),
    "tap typo": (PULSES, PULSES + "    respons: second_order\n",
                 "16: unknown key 'respons' in 'pulses.sim' (did you mean 'response'?)"),
    "tap damping": (PULSES, PULSES + "    response: second_order\n    damping: 1.2\n",
                    "17: 'damping' must be in (0, 1) for response second_order"),
    "servo list": (TABLE, TABLE + "    natural_hz: [4, 5]\n", "7: 'natural_hz' must have 3 entries, has 2"),
    "servo range": (TABLE, "    damping: [0.6, 0.6, 3]\n", "6: 'damping' entries must be in [0.05, 2]"),
    "servo typo": (TABLE, "    dampng: 0.6\n",
                   "6: unknown key 'dampng' in 'table.sim' (did you mean 'damping'?)"),
    "imu typo": (IMU, IMU + "    gyro_bias_deg_hr: [1, 2, 3]\n",
                 "12: unknown key 'gyro_bias_deg_hr' in 'imu.sim' (did you mean 'gyro_bias_deg_h'?)"),
    "imu matrix": (IMU, IMU + "    accel_misalignment_urad: [[0, 1, 2], [0, 0], [1, 1, 0]]\n",
                   "12: 'accel_misalignment_urad' must be a 3x3 list of rows of numbers (row 2 is [0, 0]) "
                   "(e.g. [[0, 1, 0], [0, 0, 0], [-2, 0, 0]])"),
    "imu vector": (IMU, IMU + "    accel_bias_mg: [1, 2]\n", "12: 'accel_bias_mg' must have 3 entries, has 2"),
    "imu negative noise": (IMU, "    gyro_arw_deg_rth: -0.2\n",
                           "11: 'gyro_arw_deg_rth' = -0.2 is below its minimum 0"),
    "gm without tau": (IMU, IMU + "    gyro_gm:\n      - {sigma_deg_h: 3}\n",
                       "13: 'imu.sim.gyro_gm' entry 1 is missing 'tau_c_s' (add a line 'tau_c_s: ...')"),
    "gm typo": (IMU, IMU + "    gyro_gm:\n      - sigma_deg_h: 3\n        tau_c: 100\n",
                "14: unknown key 'tau_c' in 'imu.sim.gyro_gm' entry 1 (did you mean 'tau_c_s'?)"),
    "gm zero tau": (IMU, IMU + "    accel_gm:\n      - {sigma_mg: 0.1, tau_c_s: 300}\n"
                    "      - {sigma_mg: 0.1, tau_c_s: 0}\n",
                    "14: 'tau_c_s' must be longer than zero (give the term's correlation time in s, "
                    "e.g. tau_c_s: 300)"),
    "gm SI key in field units": (IMU, IMU + "    gyro_gm:\n      - {sigma_rad_per_s: 1e-5, tau_c_s: 10}\n",
                                 "13: unknown key 'sigma_rad_per_s' in 'imu.sim.gyro_gm' entry 1 "
                                 "(did you mean 'sigma_deg_h'?)"),
    "gm not a list": (IMU, IMU + "    gyro_gm: {sigma_deg_h: 3, tau_c_s: 10}\n",
                      "12: 'gyro_gm' must be a list, got a mapping"),
    "gm entry": (IMU, IMU + "    gyro_gm: [3, 10]\n",
                 "12: 'imu.sim.gyro_gm' entry 1 must be a mapping (key: value lines), got 3"),
    "thermal typo": (IMU, IMU + "    thermal:\n      hysteresis: {width_k: 2}\n",
                     "13: unknown key 'width_k' in 'imu.sim.thermal.hysteresis' (did you mean 'width_K'?)"),
    "thermal section": (IMU, IMU + "    thermal:\n      rate: 3\n",
                        "13: 'imu.sim.thermal.rate' must be a mapping (key: value lines), got int 3"),
    "profile name": (IMU, "    profile: mti_clas\n",
                     "11: 'profile' = 'mti_clas' is not allowed (did you mean 'mti_class'?)"),
    "profile gm typo": (IMU, "    profile: mti_class\n    overrides:\n      gyro:\n        noise:\n"
                        "          gm: [{sigma_rad_per_s: 1.0e-5, tau_c: 10}]\n",
                        "15: unknown key 'tau_c' in imu.sim.overrides.gyro.noise.gm entry 1 "
                        "(did you mean 'tau_c_s'?; keys, units and defaults: docs/emulator.md sections 3-5)"),
    "profile gm sigma": (IMU, "    profile: mti_class\n    overrides:\n      accel:\n        noise:\n"
                         "          gm:\n            - {sigma_m_per_s2: -1.0e-5, tau_c_s: 10}\n",
                         "16: imu.sim.overrides.accel.noise.gm entry 1.sigma_m_per_s2 must be a number >= 0, "
                         "got -1e-05 (keys, units and defaults: docs/emulator.md sections 3-5)"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_malformed_sim_section_is_one_error_at_its_line(tmp_path: Path, case: str) -> None:
    old, new, expected = CASES[case]
    assert TEMPLATE.count(old) == 1
    path = tmp_path / "rig.yaml"
    path.write_text(TEMPLATE.replace(old, new))
    with pytest.raises(InputError) as info:
        with open_rig(load_config(path)):
            pass
    assert str(info.value) == f"{path}:{expected}"


def test_the_template_itself_is_valid(tmp_path: Path) -> None:
    path = tmp_path / "rig.yaml"
    path.write_text(TEMPLATE)
    with open_rig(load_config(path)) as (_rig, truth):
        assert truth["pulses"]["taps"]["axis"] == 2


@pytest.mark.parametrize("profiles, expected", [
    ("random: {base: p}\n", "1: the profile file is missing 'profiles' (add a line 'profiles: ...')"),
    ("profiles: [p]\n", "1: 'profiles' must be a mapping (key: value lines), got a list"),
    ("profiles: {p: {rate_hz: 100}}\nrandom: {base: p, noise_sprad: 2}\n",
     "2: unknown key 'noise_sprad' in random (did you mean 'noise_spread'?; keys, units and defaults: "
     "docs/emulator.md sections 3-5)"),
])
def test_a_malformed_profiles_file_is_an_error_in_that_file(tmp_path: Path, profiles: str, expected: str) -> None:
    prof = tmp_path / "mine.yaml"
    prof.write_text(profiles)
    path = tmp_path / "rig.yaml"
    path.write_text(TEMPLATE.replace(IMU, "    profile: p\n    profiles_file: mine.yaml\n"))
    with pytest.raises(InputError) as info:
        with open_rig(load_config(path)):
            pass
    assert str(info.value) == f"{prof}:{expected}"
