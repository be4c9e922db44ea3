"""A procedure with a `taps` step on a config without a pulse input -- the natural first try,
`rigctl run procedures/taps.yaml` on the default emulator (configs/sim.yaml: no tap hammer, no
mark input): `validate` and `run` say so in one warning line naming the step, the config and
the fix (--config configs/sim-taps.yaml). Before, both passed silently and the run ended with
'sync: 0 pulses recorded (tap at least 3 times with the pulse input on)'."""
from __future__ import annotations

import contextlib
import io

import yaml

from helpers import ROOT

from rigctl import cli


def _validate(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(["validate", *argv])
    return code, out.getvalue(), err.getvalue()


def test_taps_on_a_config_without_pulses_is_flagged():
    taps = str(ROOT / "procedures" / "taps.yaml")
    # which configs have a pulse input, read from the YAML here, not from rigctl's config model
    pulses = {name: (yaml.safe_load((ROOT / "configs" / name).read_text()).get("pulses") or {}).get("driver", "none")
              for name in ("sim.yaml", "sim-taps.yaml")}
    assert pulses == {"sim.yaml": "none", "sim-taps.yaml": "sim"}
    code, out, err = _validate(taps)
    lines = err.strip().splitlines()
    assert code == 0 and out.rstrip().endswith("valid")
    assert len(lines) == 1 and lines[0].startswith("warning: ") and "(taps)" in lines[0], err
    assert "sim.yaml" in lines[0] and "--config configs/sim-taps.yaml" in lines[0]
    code, _out, err = _validate(taps, "--config", str(ROOT / "configs" / "sim-taps.yaml"))
    assert code == 0 and err == ""
    code, _out, err = _validate(str(ROOT / "procedures" / "24pos.yaml"))  # no taps step: nothing to say
    assert code == 0 and err == ""
