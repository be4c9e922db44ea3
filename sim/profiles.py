"""IMU device profiles for the emulator (configs/imu-profiles.yaml) and the seeded random-truth mode.

A profile is a plain mapping (SI values, units in key names; layout documented in the YAML file)
that :meth:`rigctl.sim.error_model.ImuErrorModel.from_profile` consumes::

    prof = get_profile("mti_class")                 # or consumer_mems, tactical, declared_only
    prof = get_profile("random", seed=7)            # parameters drawn around the `random.base` profile
    model = ImuErrorModel.from_profile(prof, seed=1)

Random truth: noise coefficients (keys starting Q_, N_, B_, K_, R_) log-uniform in
[x/s, x*s] (s = noise_spread); signed error parameters (biases, scale errors, misalignments,
temperature coefficients, g-sensitivity, asymmetry, nonlinearity, lever arm) normal with zero
mean and the base field's RMS as standard deviation; structural settings (rates, bandwidths,
time constants, switches) are kept. The YAML is read with yaml.safe_load only.
"""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

DEFAULT_PATH = Path(__file__).resolve().parent.parent / "configs" / "imu-profiles.yaml"
NOISE_PREFIXES = ("Q_", "N_", "B_", "K_", "R_")
SIGNED_KEYS = {
    "bias_rad_per_s", "bias_m_per_s2", "scale_error", "misalignment_rad", "quadratic_per_m_per_s2",
    "gyro_bias_tc_rad_per_s_per_K", "gyro_scale_tc_per_K", "accel_bias_tc_m_per_s2_per_K", "accel_scale_tc_per_K",
    "G_rad_per_s_per_m_per_s2", "anisoelastic_rad_per_s_per_m2_per_s4", "asymmetry", "k2_per_rad_per_s",
    "k3_per_rad2_per_s2", "r_m", "nonorth_rad", "level_x_rad", "level_y_rad", "north_rad",
}
TEXT_KEYS = {"description", "name", "base"}


def _coerce(node: Any, key: str = "") -> Any:
    """Turn numeric strings (YAML 1.1 reads 1e-3 as text) into floats; reject other text values."""
    if isinstance(node, dict):
        return {k: _coerce(v, str(k)) for k, v in node.items()}
    if isinstance(node, list):
        return [_coerce(v, key) for v in node]
    if isinstance(node, str) and key not in TEXT_KEYS:
        try:
            return float(node)
        except ValueError as exc:
            raise ValueError(f"profile value {key!r} = {node!r} is not a number") from exc
    return node


def load_profiles(path: str | Path | None = None) -> dict:
    """The YAML document as a dict: {'profiles': {name: profile}, 'random': {...}}."""
    with open(path or DEFAULT_PATH, encoding="utf-8") as fh:
        doc = yaml.safe_load(fh)
    if not isinstance(doc, dict) or "profiles" not in doc:
        raise ValueError("profile file must be a mapping with a 'profiles' key")
    return _coerce(doc)


def profile_names(path: str | Path | None = None) -> list[str]:
    """Named profiles in the file (plus 'random')."""
    return sorted(load_profiles(path)["profiles"]) + ["random"]


def get_profile(name: str, seed: int | None = None, path: str | Path | None = None) -> dict:
    """A deep copy of profile `name` (with 'name' set); 'random' draws one with `seed` (default 0)."""
    doc = load_profiles(path)
    if name == "random":
        cfg = doc.get("random", {}) or {}
        base = doc["profiles"][cfg.get("base", "mti_class")]
        prof = random_truth(base, 0 if seed is None else seed, float(cfg.get("noise_spread", 2.0)))
        prof["name"] = f"random(base={cfg.get('base', 'mti_class')}, seed={0 if seed is None else seed})"
        return prof
    if name not in doc["profiles"]:
        raise KeyError(f"unknown IMU profile {name!r}; known: {sorted(doc['profiles'])}")
    prof = copy.deepcopy(doc["profiles"][name])
    prof["name"] = name
    return prof


def random_truth(base: Mapping[str, Any], seed: int, noise_spread: float = 2.0) -> dict:
    """Draw a profile around `base` (see module docstring). Deterministic for a given seed."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x7247]))
    log_s = np.log(noise_spread)

    def draw(node: Any, key: str) -> Any:
        if isinstance(node, dict):
            return {k: draw(v, str(k)) for k, v in sorted(node.items())}
        if key.startswith(NOISE_PREFIXES) and isinstance(node, (int, float)) and not isinstance(node, bool):
            return float(node) * float(np.exp(rng.uniform(-log_s, log_s)))
        if key in SIGNED_KEYS:
            arr = np.asarray(node, dtype=float)
            rms = float(np.sqrt(np.mean(arr**2)))
            out = rng.standard_normal(arr.shape) * rms
            if key == "misalignment_rad":
                out = out * (1 - np.eye(3))
            return out.tolist() if arr.ndim else float(out)
        return copy.deepcopy(node)

    return draw(dict(base), "")
