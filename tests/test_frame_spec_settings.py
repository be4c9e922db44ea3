"""The declared frame format (``imu.frame``) on the typed settings (rigctl/config/frame_spec.py:
BinaryFrameSettings / CsvFrameSettings, one class per field kind, checksum and length): more
malformed frames, each refused with its exact 'FILE:LINE: message (hint)' (tests/test_frame_decl.py
holds the first fifteen)."""
from __future__ import annotations

import pytest

from rigctl.config.frame_spec import parse_frame_spec
from rigctl.errors import InputError
from rigctl.yamlio import load_text

FIELDS = """fields:
  - {name: counter, type: H}
  - {name: gyro_x, type: i, scale: 1.0e-8, unit: rad/s}
  - {name: gyro_y, type: i, scale: 1.0e-8, unit: rad/s}
  - {name: gyro_z, type: i, scale: 1.0e-8, unit: rad/s}
  - {name: accel_x, type: i, scale: 1.0e-7, unit: m/s^2}
  - {name: accel_y, type: i, scale: 1.0e-7, unit: m/s^2}
  - {name: accel_z, type: i, scale: 1.0e-7, unit: m/s^2}
"""
COLUMNS = FIELDS.replace(", type: H", "").replace(", type: i", "")

CASES = [
    ("sync: AA\n" + FIELDS + "  - {name: pad, type: 0x}\n", "11: 'type' 0x pads nothing (remove the entry or give e.g. 2x)"),
    ("sync: AA\n" + FIELDS + "  - [name, st]\n", "11: 'fields' entry 8 must be a mapping (key: value lines), got "
     "['name', 'st'] (e.g. {name: gx, type: i, scale: 1.0e-7, unit: rad/s})"),
    ("sync: AA\n" + FIELDS + "  - {name: st, type: B, colur: red}\n",
     "11: unknown key 'colur' in 'fields' entry 8 (allowed: name, scale, unit, type, value)"),
    ("sync: AA\n" + FIELDS + "checksum: {type: crc32, from: 99}\n", "11: 'from' = 99 is above its maximum 26"),
    ("sync: AA\n" + FIELDS + "  - {name: len, type: B, value: 7}\nlength: {field: len}\n",
     "12: field 'len' has value 7 but the frame is 28 bytes (remove 'value' (the length is checked anyway))"),
    ("sync: AA\n", "2: 'frame' (binary) is missing 'fields' (add a line 'fields: ...')"),
    ("format: csv\n" + FIELDS, "4: a csv column has no 'type' (every column is a decimal number) (remove 'type')"),
    ("format: csv\nprefix: IMU\nchecksum: nmea\n" + COLUMNS, "4: an NMEA checksum covers the bytes after '$' "
     "(start the prefix with '$' (e.g. prefix: $IMU) or use checksum: none)"),
    ("sync: AA\n" + FIELDS + "  - {name: temperature, type: h, unit: K}\n",
     "11: 'unit' = 'K' is not allowed (choose one of: degC)"),
]


@pytest.mark.parametrize("frame, expected", CASES, ids=[c[1][:40] for c in CASES])
def test_a_malformed_frame_is_one_error_at_its_line(frame: str, expected: str) -> None:
    d = load_text("frame:\n" + "".join(f"  {line}\n" for line in frame.splitlines()), "f.yaml")
    with pytest.raises(InputError) as e:
        parse_frame_spec(d)
    assert str(e.value) == f"f.yaml:{expected}"


def test_pads_length_field_and_checksum_start_are_placed() -> None:
    """Offsets counted by hand: 1 sync byte, counter 2, six int32 24, 3 pad bytes, the length
    byte; CRC-16 after it (init 0: XMODEM) from byte 0."""
    frame = "sync: AA\n" + FIELDS + ("  - {name: pad, type: 3x}\n  - {name: len, type: B}\n"
                                     "length: {field: len, counts: fields}\nchecksum: {type: crc16-ccitt, init: 0, from: 0}\n")
    spec = parse_frame_spec(load_text("frame:\n" + "".join(f"  {x}\n" for x in frame.splitlines()), "f.yaml"))
    assert spec.length == 1 + 2 + 24 + 3 + 1 + 2
    assert spec.field("len").offset == 30 and spec.field("len").value == 2 + 24 + 3 + 1
    assert spec.field("pad").size == 3 and spec.checksum_init == 0 and spec.checksum_from == 0
