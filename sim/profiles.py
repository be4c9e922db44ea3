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
import difflib
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from rigctl.solvers.noise_coefficients import CONFIG_KEYS
from rigctl.yamlio import InputError, LocDict, LocList, load_file

DEFAULT_PATH = Path(__file__).resolve().parent.parent / "configs" / "imu-profiles.yaml"
NOISE_PREFIXES = ("Q_", "N_", "B_", "K_", "R_")
SIGNED_KEYS = {
    "bias_rad_per_s", "bias_m_per_s2", "scale_error", "misalignment_rad", "quadratic_per_m_per_s2",
    "gyro_bias_tc_rad_per_s_per_K", "gyro_scale_tc_per_K", "accel_bias_tc_m_per_s2_per_K", "accel_scale_tc_per_K",
    "G_rad_per_s_per_m_per_s2", "anisoelastic_rad_per_s_per_m2_per_s4", "asymmetry", "k2_per_rad_per_s",
    "k3_per_rad2_per_s2", "r_m", "nonorth_rad", "level_x_rad", "level_y_rad", "north_rad",
}
TEXT_KEYS = {"description", "name", "base"}


def _like(node: Any, new: Any) -> Any:
    """``new`` with the source location of ``node`` (LocDict / LocList), if it has one."""
    if isinstance(node, LocDict):
        out = LocDict(new)
        out.file, out.line, out.key_lines = node.file, node.line, dict(node.key_lines)
        return out
    if isinstance(node, LocList):
        out = LocList(new)
        out.file, out.line, out.item_lines = node.file, node.line, list(node.item_lines)
        return out
    return new


def _coerce(node: Any, key: str = "") -> Any:
    """Turn numeric strings (YAML 1.1 reads 1e-3 as text) into floats; reject other text values.
    Source locations (file, line) are kept."""
    if isinstance(node, dict):
        return _like(node, {k: _coerce(v, str(k)) for k, v in node.items()})
    if isinstance(node, list):
        return _like(node, [_coerce(v, key) for v in node])
    if isinstance(node, str) and key not in TEXT_KEYS:
        try:
            return float(node)
        except ValueError as exc:
            raise ValueError(f"profile value {key!r} = {node!r} is not a number") from exc
    return node


def load_profiles(path: str | Path | None = None) -> dict:
    """The YAML document as a dict: {'profiles': {name: profile}, 'random': {...}} (safe
    loader; mappings are LocDicts that know their file and lines)."""
    doc = load_file(path or DEFAULT_PATH)
    if not isinstance(doc, dict) or not isinstance(doc.get("profiles"), dict):
        raise ValueError("profile file must be a mapping with a 'profiles' mapping")
    _check_keys(doc, {"profiles": None, "random": None}, "the profile file")
    if doc.get("random") is not None:
        _check_mapping(doc["random"], RANDOM_SCHEMA, "random", doc, "random")
    try:
        return _coerce(doc)
    except ValueError:
        for name, prof in doc["profiles"].items():  # say where the bad value is
            _check_mapping(prof, PROFILE_SCHEMA, f"profile {name!r}", doc["profiles"], name)
        raise


def profile_names(path: str | Path | None = None) -> list[str]:
    """Named profiles in the file (plus 'random')."""
    return sorted(load_profiles(path)["profiles"]) + ["random"]


def get_profile(name: str, seed: int | None = None, path: str | Path | None = None) -> dict:
    """A deep copy of profile `name` (with 'name' set); 'random' draws one with `seed` (default 0)."""
    doc = load_profiles(path)
    if name == "random":
        cfg = doc.get("random", {}) or {}
        base_name = cfg.get("base", "mti_class")
        if base_name not in doc["profiles"]:
            raise _error(cfg, "base", f"random.base {base_name!r} is not a profile of the file",
                         f"known: {sorted(doc['profiles'])}", doc)
        base = doc["profiles"][base_name]
        _check_mapping(base, PROFILE_SCHEMA, f"profile {base_name!r}", doc["profiles"], base_name)
        prof = random_truth(base, 0 if seed is None else seed, float(cfg.get("noise_spread", 2.0)))
        prof["name"] = f"random(base={cfg.get('base', 'mti_class')}, seed={0 if seed is None else seed})"
        return prof
    if name not in doc["profiles"]:
        raise KeyError(f"unknown IMU profile {name!r}; known: {sorted(doc['profiles'])}")
    _check_mapping(doc["profiles"][name], PROFILE_SCHEMA, f"profile {name!r}", doc["profiles"], name)
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


# ---------------------------------------------------------------------------- schema
# The keys of a profile (docs/emulator.md sections 3-5; configs/imu-profiles.yaml spells them
# out). A leaf is a kind: see _LEAF. Every key is optional except REQUIRED ones of an enabled
# effect.
_NOISE = {"flicker_tau_min_s": "pos", "flicker_tau_max_s": "pos", "flicker_pairs_per_decade": "pos"}
# the term keys are rigctl.solvers.noise_coefficients.CONFIG_KEYS (one spelling, read by from_config)
_GYRO_NOISE = {**{k: "coef" for k in CONFIG_KEYS["gyro"].values()}, **_NOISE}
_ACCEL_NOISE = {**{k: "coef" for k in CONFIG_KEYS["accel"].values()}, **_NOISE}
EFFECTS_SCHEMA: dict[str, dict[str, str]] = {
    "warmup": {"T0_degC": "num", "dT_degC": "num", "tau_s": "pos", "T_ref_degC": "num",
               "gyro_bias_tc_rad_per_s_per_K": "vec3", "gyro_scale_tc_per_K": "vec3",
               "accel_bias_tc_m_per_s2_per_K": "vec3", "accel_scale_tc_per_K": "vec3",
               "temp_noise_degC": "nonneg", "temp_lsb_degC": "nonneg"},
    "turn_on_bias": {"gyro_sigma_rad_per_s": "nonneg", "accel_sigma_m_per_s2": "nonneg"},
    "g_sensitivity": {"G_rad_per_s_per_m_per_s2": "mat3", "anisoelastic_rad_per_s_per_m2_per_s4": "mat3"},
    "accel_scale_asymmetry": {"asymmetry": "vec3"},
    "gyro_nonlinearity": {"k2_per_rad_per_s": "vec3", "k3_per_rad2_per_s2": "vec3"},
    "lever_arm": {"r_m": "vec3"},
    "time_delay": {"delay_s": "nonneg"},
    "vibration": {"freqs_hz": "nums", "accel_amp_m_per_s2": "rows3", "gyro_amp_rad_per_s": "rows3"},
    "clock": {"drift_ppm": "num", "wander_ppm": "nonneg", "wander_tau_s": "pos",
              "drop_probability": "prob", "drop_max_burst": "count"},
    "table_geometry": {"nonorth_rad": "vec3", "level_x_rad": "num", "level_y_rad": "num", "north_rad": "num"},
}
#: keys an enabled effect must have (no default)
REQUIRED = {"warmup": ("T0_degC", "dT_degC", "tau_s"), "accel_scale_asymmetry": ("asymmetry",),
            "lever_arm": ("r_m",), "time_delay": ("delay_s",)}
PROFILE_SCHEMA: dict[str, Any] = {
    "description": "text", "name": "text", "rate_hz": "pos", "power_on_time_s": "nonneg",
    "frontend": {"internal_rate_hz": "pos?", "filter_order": "count", "gyro_bandwidth_hz": "pos?",
                 "accel_bandwidth_hz": "pos?", "gyro_lsb_rad_per_s": "nonneg?",
                 "gyro_full_scale_rad_per_s": "pos?", "accel_lsb_m_per_s2": "nonneg?",
                 "accel_full_scale_m_per_s2": "pos?"},
    "gyro": {"noise": _GYRO_NOISE, "bias_rad_per_s": "vec3", "scale_error": "vec3", "misalignment_rad": "mat3"},
    "accel": {"noise": _ACCEL_NOISE, "bias_m_per_s2": "vec3", "scale_error": "vec3",
              "misalignment_rad": "mat3", "quadratic_per_m_per_s2": "vec3"},
    "effects": {name: {"enabled": "bool", **keys} for name, keys in EFFECTS_SCHEMA.items()},
}
RANDOM_SCHEMA = {"base": "text", "noise_spread": "pos"}

#: leaf kind -> (check, what it must be)
_LEAF: dict[str, tuple[Any, str]] = {}


def _num(x: Any) -> float | None:
    """x as a finite float (numeric strings accepted, as YAML 1.1 reads 1e-3), else None."""
    if isinstance(x, bool):
        return None
    if isinstance(x, (int, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, str):
        try:
            v = float(x)
        except ValueError:
            return None
        return v if math.isfinite(v) else None
    return None


def _nums(x: Any, n: int | None = None) -> bool:
    return isinstance(x, list) and (n is None or len(x) == n) and all(_num(v) is not None for v in x)


def _scalar(test: Any) -> Any:
    return lambda x: _num(x) is not None and test(_num(x))


_LEAF.update({
    "text": (lambda x: isinstance(x, str), "text"),
    "bool": (lambda x: isinstance(x, bool), "true or false"),
    "num": (_scalar(lambda v: True), "a number"),
    "pos": (_scalar(lambda v: v > 0), "a number > 0"),
    "nonneg": (_scalar(lambda v: v >= 0), "a number >= 0"),
    "prob": (_scalar(lambda v: 0 <= v <= 1), "a probability in [0, 1]"),
    "count": (_scalar(lambda v: v >= 1 and v == int(v)), "a whole number >= 1"),
    "pos?": (lambda x: x is None or _LEAF["pos"][0](x), "a number > 0, or null (none)"),
    "nonneg?": (lambda x: x is None or _LEAF["nonneg"][0](x), "a number >= 0, or null (none)"),
    "vec3": (lambda x: _num(x) is not None or _nums(x, 3), "a number or a list of 3 numbers [x, y, z]"),
    "coef": (lambda x: (_num(x) is not None and _num(x) >= 0)
             or (_nums(x, 3) and all(_num(v) >= 0 for v in x)),
             "a number >= 0 or a list of 3 such numbers [x, y, z]"),
    "mat3": (lambda x: isinstance(x, list) and len(x) == 3 and all(_nums(r, 3) for r in x),
             "a 3x3 list of rows [[..], [..], [..]]"),
    "nums": (lambda x: _nums(x), "a list of numbers"),
    "rows3": (lambda x: isinstance(x, list) and all(_nums(r, 3) for r in x),
              "a list of [x, y, z] rows, one per frequency"),
})

DOC_HINT = "keys, units and defaults: docs/emulator.md sections 3-5"


def _error(node: Any, key: Any, message: str, hint: str, fallback: Any = None) -> InputError:
    """An InputError at node[key] (file and line when the node knows them, else the fallback)."""
    for obj, k in ((node, key), (fallback, None)):
        if isinstance(obj, (LocDict, LocList)):
            line = obj.line_of(k) if k is not None else obj.line
            return InputError(message, obj.file, line, hint)
    return InputError(message, hint=hint)


def _check_keys(node: dict, schema: Mapping[str, Any], what: str) -> None:
    for key in node:
        if key not in schema:
            close = difflib.get_close_matches(str(key), [str(k) for k in schema], n=1)
            hint = (f"did you mean {close[0]!r}? " if close else "") + f"known keys: {', '.join(schema)}"
            raise _error(node, key, f"unknown key {key!r} in {what}", f"{hint}; {DOC_HINT}")


def _check_mapping(node: Any, schema: Mapping[str, Any], what: str, parent: Any = None,
                   key: Any = None) -> None:
    """Unknown keys and values of the wrong kind are InputErrors naming file and line."""
    if node is None:
        return
    if not isinstance(node, dict):
        raise _error(parent, key, f"{what} must be a mapping (key: value lines), got {node!r}", DOC_HINT)
    _check_keys(node, schema, what)
    for k, v in node.items():
        sub = schema[k]
        if isinstance(sub, dict):
            _check_mapping(v, sub, f"{what}.{k}", node, k)
        else:
            ok, must = _LEAF[sub]
            if not ok(v):
                raise _error(node, k, f"{what}.{k} must be {must}, got {v!r}", DOC_HINT)


def check_profile(profile: Any, what: str) -> None:
    """Check a profile (or an overrides mapping) against PROFILE_SCHEMA."""
    _check_mapping(profile, PROFILE_SCHEMA, what)


def check_merged(profile: Mapping[str, Any], overrides: Any, base: Any, what: str) -> None:
    """Checks that need the merged profile: an enabled effect has its required keys, and a
    vibration has one amplitude row per frequency. Errors point at the override that set the
    effect, else at the profile file."""
    effects = profile.get("effects") or {}
    for name, eff in effects.items():
        if not isinstance(eff, dict) or not eff.get("enabled", False):
            continue
        where, key = _deepest([overrides, base], ("effects", name))
        for req in REQUIRED.get(name, ()):
            if req not in eff:
                raise _error(where, key, f"effect {name!r} is enabled but has no {req!r} ({what})",
                             f"add '{req}: ...' to effects.{name} (units in the key name), or switch "
                             f"the effect off with 'enabled: false'; {DOC_HINT}")
        if name == "vibration":
            n = len(eff.get("freqs_hz") or [])
            for k in ("accel_amp_m_per_s2", "gyro_amp_rad_per_s"):
                if k in eff and len(eff[k]) != n:
                    raise _error(where, key, f"effects.vibration.{k} has {len(eff[k])} rows for "
                                 f"{n} frequencies ({what})", "give one [x, y, z] row per entry of freqs_hz")


def _deepest(trees: list[Any], path: tuple[str, ...]) -> tuple[Any, Any]:
    """(located mapping, key) of the last step of ``path`` in the first tree that has all of
    it (overrides before the profile file), else (the first located tree, None)."""
    for tree in trees:
        node, parent = tree, None
        for k in path:
            parent, node = node, node.get(k) if isinstance(node, dict) else None
        if node is not None and isinstance(parent, LocDict):
            return parent, path[-1]
    return next((t for t in trees if isinstance(t, LocDict)), None), None
