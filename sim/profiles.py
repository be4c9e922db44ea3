"""IMU device profiles for the emulator (configs/imu-profiles.yaml) and the seeded random-truth mode.

A profile is read as :class:`ImuProfile` (SI values, units in key names; layout documented in the
YAML file), whose fields :class:`rigctl.sim.error_model.ImuErrorModel` reads; ``imu.sim.overrides``
are read as one too and merged into it (:func:`merged`). :func:`get_profile` hands out the
ImuProfile (named, or drawn at random), and :meth:`ImuProfile.with_overrides` one changed as
``imu.sim.overrides`` change it::

    prof = get_profile("mti_class")                 # or consumer_mems, tactical, declared_only
    prof = get_profile("random", seed=7)            # parameters drawn around the `random.base` profile
    prof = get_profile("tactical").with_overrides({"effects": {"vibration": {"enabled": False}}})
    model = ImuErrorModel.from_profile(prof, seed=1)

Random truth: noise coefficients (keys starting Q_, N_, B_, K_, R_) log-uniform in
[x/s, x*s] (s = noise_spread); signed error parameters (biases, scale errors, misalignments,
temperature coefficients, g-sensitivity, asymmetry, nonlinearity, lever arm) normal with zero
mean and the base field's RMS as standard deviation; structural settings (rates, bandwidths,
time constants, switches) are kept. The YAML is read with yaml.safe_load only.
"""
from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, fields, make_dataclass, replace
from pathlib import Path
from typing import Any, ClassVar, Mapping

import numpy as np

from rigctl import schema as S
from rigctl.settings import Settings, items, mapping, parse, setting, subsection
from rigctl.solvers.noise_coefficients import (BAND_KEYS, CONFIG_KEYS, GM_KEY, GM_SIGMA_KEYS, GaussMarkov,
                                               Triad, triad)
from rigctl.yamlio import InputError, LocDict, LocList, load_file

DEFAULT_PATH = Path(__file__).resolve().parent.parent / "configs" / "imu-profiles.yaml"
NOISE_PREFIXES = ("Q_", "N_", "B_", "K_", "R_")
SIGNED_KEYS = {
    "bias_rad_per_s", "bias_m_per_s2", "scale_error", "misalignment_rad", "quadratic_per_m_per_s2",
    "gyro_bias_tc_rad_per_s_per_K", "gyro_scale_tc_per_K", "accel_bias_tc_m_per_s2_per_K", "accel_scale_tc_per_K",
    "G_rad_per_s_per_m_per_s2", "anisoelastic_rad_per_s_per_m2_per_s4", "asymmetry", "k2_per_rad_per_s",
    "k3_per_rad2_per_s2", "r_m", "nonorth_rad", "level_x_rad", "level_y_rad", "north_rad",
}


def load_profiles(path: str | Path | None = None) -> dict:
    """The YAML document as a dict: {'profiles': {name: profile}, 'random': {...}} (safe
    loader; mappings are LocDicts that know their file and lines), checked as a
    :class:`ProfileFile` (each profile is read when it is used)."""
    file = Path(path or DEFAULT_PATH)
    doc = load_file(file)
    if doc is None:
        raise InputError("the profile file is empty", str(file), hint="it needs a 'profiles:' mapping")
    parse(ProfileFile, S.require_mapping(doc, "the profile file"), "the profile file")
    return doc


def profile_names(path: str | Path | None = None) -> list[str]:
    """Named profiles in the file (plus 'random')."""
    return sorted(load_profiles(path)["profiles"]) + ["random"]


def get_profile(name: str, seed: int | None = None, path: str | Path | None = None) -> "ImuProfile":
    """Profile ``name`` (with its name set) as an :class:`ImuProfile`; 'random' draws one with
    ``seed`` (default 0) around the file's ``random.base``."""
    doc = load_profiles(path)
    if name == "random":
        cfg = parse(ProfileFile, doc, "the profile file").random
        base_name = cfg.base or "mti_class"
        if base_name not in doc["profiles"]:
            raise _error(doc.get("random"), "base", f"random.base {base_name!r} is not a profile of the file",
                         f"known: {sorted(doc['profiles'])}", doc)
        base = _read(doc["profiles"], base_name)
        seed = 0 if seed is None else seed
        prof = random_truth(base, seed, float(2.0 if cfg.noise_spread is None else cfg.noise_spread))
        return replace(prof, name=f"random(base={base_name}, seed={seed})")
    if name not in doc["profiles"]:
        raise KeyError(f"unknown IMU profile {name!r}; known: {sorted(doc['profiles'])}")
    return replace(_read(doc["profiles"], name), name=name)


def random_truth(base: Any, seed: int, noise_spread: float = 2.0) -> "ImuProfile":
    """Draw a profile around ``base`` (an :class:`ImuProfile`, or a mapping read as one; see the
    module docstring). Deterministic for a given seed: the keys a profile gives are drawn in
    the order of their names, sections included (a section's keys where its name falls)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x7247]))
    log_s = np.log(noise_spread)

    def leaf_draw(key: str, node: Any) -> Any:
        if key.startswith(NOISE_PREFIXES) and isinstance(node, (int, float)) and not isinstance(node, bool):
            return float(node) * float(np.exp(rng.uniform(-log_s, log_s)))
        if key in SIGNED_KEYS:
            arr = np.asarray(node, dtype=float)
            rms = float(np.sqrt(np.mean(arr**2)))
            out = rng.standard_normal(arr.shape) * rms
            if key == "misalignment_rad":
                out = out * (1 - np.eye(3))
            return out.tolist() if arr.ndim else float(out)
        return node

    def draw(section: Settings) -> Settings:
        new = {}
        for name, value in sorted(given(section).items()):
            new[name] = draw(value) if isinstance(value, Settings) else leaf_draw(name, value)
        return replace(section, **new)

    return draw(ImuProfile.read(base))  # type: ignore[return-value]


# ---------------------------------------------------------------------------- schema
# The keys of a profile (docs/emulator.md sections 3-5; configs/imu-profiles.yaml spells them
# out), one settings class per section (rigctl.settings); a leaf is a kind: see _LEAF. Every key
# is optional except the REQUIRED ones of an enabled effect (a rule on the merged profile:
# check_merged) and a Gauss-Markov term's two. ImuErrorModel reads a profile as ImuProfile; the
# classes also check the file's profiles and the overrides with file and line.

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


def _number_text(x: Any) -> Any:
    """``x`` with numeric text read as a float (YAML 1.1 reads 1e-3 as text), in lists too;
    numbers keep their type (an int stays an int)."""
    if isinstance(x, list):
        return [_number_text(v) for v in x]
    return float(x) if isinstance(x, str) else x


def _read_leaf(d: LocDict, key: str, default: Any = None, *, kind: str, what: str) -> Any:
    ok, must = _LEAF[kind]
    if not ok(d[key]):
        raise S.error(d, key, f"{what}.{key} must be {must}, got {d[key]!r}", DOC_HINT)
    return d[key] if kind == "text" else _number_text(d[key])


def leaf(kind: str, default: Any = None) -> Any:
    """A profile value of ``kind`` (:data:`_LEAF`) as written, numeric text read as a float;
    None: not given."""
    return setting(default, read=_read_leaf, what=True, kind=kind)


def given(section: Settings) -> dict[str, Any]:
    """The keys a profile section gives (not None), in field order: what the truth reports."""
    return {f.name: getattr(section, f.name) for f in fields(section)
            if "read" in f.metadata and getattr(section, f.name) is not None}


@dataclass(frozen=True, kw_only=True)
class ProfileSection(Settings):
    """Base of a profile's sections: an unknown key's hint names the docs."""

    HINT: ClassVar[str] = DOC_HINT
    KIND: ClassVar[str] = "leaf"


def _gm(sigma_key: str) -> type[ProfileSection]:
    """A Gauss-Markov term of a ``noise:`` section, SI: sigma (the sensor's rate unit) and Tc (s)."""
    return make_dataclass(f"GaussMarkov_{sigma_key}", [(sigma_key, Any, leaf("nonneg", MISSING)),
                                                       ("tau_c_s", Any, leaf("pos", MISSING))],
                          bases=(ProfileSection,), frozen=True, kw_only=True)


@dataclass(frozen=True, kw_only=True)
class NoiseSection(ProfileSection):
    """Base of a sensor's ``noise:`` section (fields: :func:`_noise`)."""

    SENSOR: ClassVar[str] = ""

    def coefficients(self) -> Triad:
        """The three axes' IEEE 952 coefficients (terms not given: 0; a Gauss-Markov term on
        every axis); a negative value is a ValueError."""
        sensor = self.SENSOR
        terms = {t: (0.0 if getattr(self, k) is None else getattr(self, k)) for t, k in CONFIG_KEYS[sensor].items()}
        band = {k: float(getattr(self, k)) for k in BAND_KEYS if getattr(self, k) is not None}
        axes = triad(sensor, "emulator profile", **band, **terms)
        gm = tuple(GaussMarkov(float(getattr(g, GM_SIGMA_KEYS[sensor])), float(g.tau_c_s))
                   for g in getattr(self, GM_KEY))
        return tuple(replace(m, gm=gm) for m in axes) if gm else axes  # type: ignore[return-value]

    def flicker_density(self) -> float:
        """The flicker cascade density (pole/zero pairs per decade; default 2)."""
        v = getattr(self, "flicker_pairs_per_decade")
        return 2.0 if v is None else float(v)


def _noise(sensor: str) -> type[NoiseSection]:
    """A sensor's ``noise:`` section: the IEEE 952 terms (CONFIG_KEYS, each a number or
    [x, y, z]), the flicker band and cascade density, and Gauss-Markov terms."""
    terms = [(k, Any, leaf("coef")) for k in CONFIG_KEYS[sensor].values()]
    band = [(k, Any, leaf("pos")) for k in ("flicker_tau_min_s", "flicker_tau_max_s", "flicker_pairs_per_decade")]
    gm = [(GM_KEY, Any, items(_gm(GM_SIGMA_KEYS[sensor])))]
    return make_dataclass(f"{sensor.capitalize()}Noise", terms + band + gm, bases=(NoiseSection,),
                          frozen=True, kw_only=True, namespace={"SENSOR": sensor})


@dataclass(frozen=True, kw_only=True)
class FrontendProfile(ProfileSection):
    internal_rate_hz: Any = leaf("pos?")
    filter_order: Any = leaf("count")
    gyro_bandwidth_hz: Any = leaf("pos?")
    accel_bandwidth_hz: Any = leaf("pos?")
    gyro_lsb_rad_per_s: Any = leaf("nonneg?")
    gyro_full_scale_rad_per_s: Any = leaf("pos?")
    accel_lsb_m_per_s2: Any = leaf("nonneg?")
    accel_full_scale_m_per_s2: Any = leaf("pos?")


@dataclass(frozen=True, kw_only=True)
class GyroProfile(ProfileSection):
    noise: Any = subsection(_noise("gyro"))
    bias_rad_per_s: Any = leaf("vec3")
    scale_error: Any = leaf("vec3")
    misalignment_rad: Any = leaf("mat3")


@dataclass(frozen=True, kw_only=True)
class AccelProfile(ProfileSection):
    noise: Any = subsection(_noise("accel"))
    bias_m_per_s2: Any = leaf("vec3")
    scale_error: Any = leaf("vec3")
    misalignment_rad: Any = leaf("mat3")
    quadratic_per_m_per_s2: Any = leaf("vec3")


@dataclass(frozen=True, kw_only=True)
class Effect(ProfileSection):
    """A switchable effect: ``enabled`` and its keys; REQUIRED: the keys it needs when enabled."""

    REQUIRED: ClassVar[tuple[str, ...]] = ()
    enabled: Any = leaf("bool")


@dataclass(frozen=True, kw_only=True)
class Warmup(Effect):
    REQUIRED: ClassVar[tuple[str, ...]] = ("T0_degC", "dT_degC", "tau_s")
    T0_degC: Any = leaf("num")
    dT_degC: Any = leaf("num")
    tau_s: Any = leaf("pos")
    T_ref_degC: Any = leaf("num")
    gyro_bias_tc_rad_per_s_per_K: Any = leaf("vec3")
    gyro_scale_tc_per_K: Any = leaf("vec3")
    accel_bias_tc_m_per_s2_per_K: Any = leaf("vec3")
    accel_scale_tc_per_K: Any = leaf("vec3")
    temp_noise_degC: Any = leaf("nonneg")
    temp_lsb_degC: Any = leaf("nonneg")


@dataclass(frozen=True, kw_only=True)
class TurnOnBias(Effect):
    gyro_sigma_rad_per_s: Any = leaf("nonneg")
    accel_sigma_m_per_s2: Any = leaf("nonneg")


@dataclass(frozen=True, kw_only=True)
class GSensitivity(Effect):
    G_rad_per_s_per_m_per_s2: Any = leaf("mat3")
    anisoelastic_rad_per_s_per_m2_per_s4: Any = leaf("mat3")


@dataclass(frozen=True, kw_only=True)
class AccelScaleAsymmetry(Effect):
    REQUIRED: ClassVar[tuple[str, ...]] = ("asymmetry",)
    asymmetry: Any = leaf("vec3")


@dataclass(frozen=True, kw_only=True)
class GyroNonlinearity(Effect):
    k2_per_rad_per_s: Any = leaf("vec3")
    k3_per_rad2_per_s2: Any = leaf("vec3")


@dataclass(frozen=True, kw_only=True)
class LeverArm(Effect):
    REQUIRED: ClassVar[tuple[str, ...]] = ("r_m",)
    r_m: Any = leaf("vec3")


@dataclass(frozen=True, kw_only=True)
class TimeDelay(Effect):
    REQUIRED: ClassVar[tuple[str, ...]] = ("delay_s",)
    delay_s: Any = leaf("nonneg")


@dataclass(frozen=True, kw_only=True)
class Vibration(Effect):
    freqs_hz: Any = leaf("nums")
    accel_amp_m_per_s2: Any = leaf("rows3")
    gyro_amp_rad_per_s: Any = leaf("rows3")


@dataclass(frozen=True, kw_only=True)
class ClockEffect(Effect):
    drift_ppm: Any = leaf("num")
    wander_ppm: Any = leaf("nonneg")
    wander_tau_s: Any = leaf("pos")
    drop_probability: Any = leaf("prob")
    drop_max_burst: Any = leaf("count")


@dataclass(frozen=True, kw_only=True)
class TableGeometry(Effect):
    nonorth_rad: Any = leaf("vec3")
    level_x_rad: Any = leaf("num")
    level_y_rad: Any = leaf("num")
    north_rad: Any = leaf("num")


#: effect name -> its settings
EFFECTS: dict[str, type[Effect]] = {
    "warmup": Warmup, "turn_on_bias": TurnOnBias, "g_sensitivity": GSensitivity,
    "accel_scale_asymmetry": AccelScaleAsymmetry, "gyro_nonlinearity": GyroNonlinearity,
    "lever_arm": LeverArm, "time_delay": TimeDelay, "vibration": Vibration, "clock": ClockEffect,
    "table_geometry": TableGeometry}
EffectsProfile = make_dataclass("EffectsProfile", [(k, Any, subsection(c)) for k, c in EFFECTS.items()],
                                bases=(ProfileSection,), frozen=True, kw_only=True)


@dataclass(frozen=True, kw_only=True)
class ImuProfile(ProfileSection):
    """One device profile (a ``profiles:`` entry, or ``imu.sim.overrides``)."""

    description: Any = leaf("text")
    name: Any = leaf("text")
    rate_hz: Any = leaf("pos")
    power_on_time_s: Any = leaf("nonneg")
    frontend: Any = subsection(FrontendProfile)
    gyro: Any = subsection(GyroProfile)
    accel: Any = subsection(AccelProfile)
    effects: Any = subsection(EffectsProfile)

    @classmethod
    def read(cls, profile: Any, what: str = "the IMU profile") -> "ImuProfile":
        """``profile`` (an ImuProfile, or a mapping as in the profiles file) as an ImuProfile."""
        if isinstance(profile, ImuProfile):
            return profile
        return parse(cls, profile if isinstance(profile, LocDict) else LocDict(profile), what)

    def with_overrides(self, overrides: Mapping[str, Any], what: str = "the overrides") -> "ImuProfile":
        """This profile changed as ``imu.sim.overrides`` change it (:func:`merged`): the keys
        ``overrides`` gives replaced, a section given as a mapping merged key by key, a key or a
        whole section given as None cleared; checked as the overrides are (:func:`check_profile`,
        :func:`check_merged`). For code that varies a profile (tests, benchmarks)::

            get_profile("consumer_mems").with_overrides({"rate_hz": 10, "effects": {"vibration": {"enabled": False}}})

        To replace a section wholly, clear it first: ``.with_overrides({"effects": None})
        .with_overrides({"effects": {...}})``."""
        out = merged(self, overrides, check_profile(overrides, what))
        check_merged(out, overrides, None, what)
        return out


@dataclass(frozen=True, kw_only=True)
class RandomProfile(ProfileSection):
    """The file's ``random:`` section: the profile drawn around and the spread of its noise."""

    base: Any = leaf("text")
    noise_spread: Any = leaf("pos")


@dataclass(frozen=True, kw_only=True)
class ProfileFile(ProfileSection):
    """A profiles file (configs/imu-profiles.yaml): the named profiles (each read as
    :class:`ImuProfile` when it is used) and the random-truth mode's settings."""

    profiles: Any = mapping()
    random: Any = subsection(RandomProfile, "random")


#: the effects' required keys (when enabled)
REQUIRED = {name: c.REQUIRED for name, c in EFFECTS.items() if c.REQUIRED}


def _tree(cls: type[Settings]) -> dict[str, Any]:
    """The key tree of a profile section: {key: kind or sub-tree} (for docs and tests)."""
    out: dict[str, Any] = {}
    for f in fields(cls):
        if "read" not in f.metadata:
            continue
        sub = f.default if isinstance(f.default, Settings) else None
        out[f.name] = _tree(type(sub)) if sub is not None else f.metadata["check"].get("kind", "items")
    return out


PROFILE_SCHEMA: dict[str, Any] = _tree(ImuProfile)
RANDOM_SCHEMA: dict[str, Any] = _tree(RandomProfile)
EFFECTS_SCHEMA: dict[str, Any] = PROFILE_SCHEMA["effects"]


def _error(node: Any, key: Any, message: str, hint: str, fallback: Any = None) -> InputError:
    """An InputError at node[key] (file and line when the node knows them, else the fallback)."""
    for obj, k in ((node, key), (fallback, None)):
        if isinstance(obj, (LocDict, LocList)):
            line = obj.line_of(k) if k is not None else obj.line
            return InputError(message, obj.file, line, hint)
    return InputError(message, hint=hint)


def check_profile(profile: Any, what: str) -> "ImuProfile":
    """A profile (or an overrides mapping) read as :class:`ImuProfile` (errors with file and line)."""
    if not isinstance(profile, dict):
        raise _error(None, None, f"{what} must be a mapping (key: value lines), got {profile!r}", DOC_HINT)
    return parse(ImuProfile, profile if isinstance(profile, LocDict) else LocDict(profile), what)


def _read(profiles: Any, name: str) -> "ImuProfile":
    """Profile ``name`` of the file's ``profiles:`` mapping as an ImuProfile (errors at its lines)."""
    node = profiles[name]
    if not isinstance(node, dict):
        raise _error(profiles, name, f"profile {name!r} must be a mapping (key: value lines), got {node!r}",
                     DOC_HINT)
    return parse(ImuProfile, node if isinstance(node, LocDict) else LocDict(node), f"profile {name!r}")


def merged(base: Settings, overrides: Mapping[str, Any], read: Settings) -> Any:
    """``base`` with the keys ``overrides`` gives replaced (a section given as a mapping is merged
    key by key; a key given as null is null); ``read``: the overrides read as the same settings."""
    new = {}
    for f in fields(base):
        if "read" not in f.metadata or f.name not in overrides:
            continue
        old, over = getattr(base, f.name), overrides[f.name]
        new[f.name] = (merged(old, over, getattr(read, f.name))
                       if isinstance(old, Settings) and isinstance(over, dict) else getattr(read, f.name))
    return replace(base, **new)


def check_merged(profile: "ImuProfile", overrides: Any, base: Any, what: str) -> None:
    """Checks that need the merged profile: an enabled effect has its required keys, and a
    vibration has one amplitude row per frequency. Errors point at the override that set the
    effect, else at the profile file (``base``: the profile's mapping, if it has one)."""
    for name in EFFECTS:
        eff = getattr(profile.effects, name)
        if not eff.enabled:
            continue
        where, key = _deepest([overrides, base], ("effects", name))
        for req in eff.REQUIRED:
            if getattr(eff, req) is None:
                raise _error(where, key, f"effect {name!r} is enabled but has no {req!r} ({what})",
                             f"add '{req}: ...' to effects.{name} (units in the key name), or switch "
                             f"the effect off with 'enabled: false'; {DOC_HINT}")
        if name == "vibration":
            n = len(eff.freqs_hz or [])
            for k in ("accel_amp_m_per_s2", "gyro_amp_rad_per_s"):
                rows = getattr(eff, k)
                if rows is not None and len(rows) != n:
                    raise _error(where, key, f"effects.vibration.{k} has {len(rows)} rows for "
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
