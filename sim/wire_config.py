"""Rig configs that point the wired drivers at running emulated hardware.

``wire_config(base, hw, ...)`` takes a config mapping (configs/sim.yaml, or the template
configs/sim-wire.yaml whose ``port: auto`` entries are placeholders) and returns a copy in which
every device talks over the wire to ``hw`` (a :class:`rigctl.sim.hardware.Hardware`): the clock
is ``scaled`` at the hardware's speed, and the table, IMU and pulse sections carry the driver and
the endpoints (pty symlinks, ``socket://`` URLs, Modbus host/port). The emulator sections
(``table.sim``, ``imu.sim``) are kept, so the result also works as ``rigctl sim up --config``.
"""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml

KEEP = ("limits", "sim", "rate_hz")

#: the reply timeout of the table and the chamber on emulated hardware, wall s: the emulator
#: shares the host (in the tests, the process) with its client, so its replies wait for the
#: host's scheduler as well --
#: at load 15-18 on 2 cores more than the 0.5 s of a real controller's default (wired 24-position
#: runs paused on 'no reply to :READ:ALL? ... within 0.5 s' and re-ran steps). The same allowance
#: as the IMU port's flow-control wait (sim/hardware.py FlowPtyEndpoint.write_timeout_s). The
#: chamber's was 0.5 s (Watlow) and 1.0 s (SCPI): the soaks paused on 'chamber link lost: ... No
#: response received' and re-ran their chamber-wait step (set points 15, 15, 25, ...).
REPLY_TIMEOUT_S = 1.5


def _keep(section: dict | None) -> dict:
    return {k: v for k, v in (section or {}).items() if k in KEEP}


def wire_config(base: dict[str, Any], hw, *, table: str | None = None, link: str | None = None,
                pulses: str | None = None, imu_options: dict | None = None,
                chamber: str | None = None) -> dict[str, Any]:
    """A config dict for a wired rig on ``hw``.

    table: ``acl`` | ``modbus`` (default: the base's wired driver, else acl); link: ``pty`` | ``tcp``
    for acl, ``tcp`` | ``rtu`` for modbus (default pty / tcp); pulses: ``novatel`` | ``none``
    (default: the base's, else novatel); chamber: ``watlow-rtu`` | ``watlow-tcp`` | ``scpi`` (the
    emulated chamber over Modbus RTU on a pty, Modbus TCP, or SCPI through PyVISA), default none.
    """
    d = copy.deepcopy(base)
    t_in, i_in, p_in = d.get("table") or {}, d.get("imu") or {}, d.get("pulses") or {}
    table = table or (t_in.get("driver") if t_in.get("driver") in ("acl", "modbus") else "acl")
    link = link or t_in.get("transport") or ("pty" if table == "acl" else "tcp")
    pulses = pulses or (p_in.get("driver") if p_in.get("driver") in ("novatel", "none") else "novatel")
    ep = hw.endpoints
    t = _keep(t_in)
    if table == "acl":
        if link not in ("pty", "tcp"):
            raise ValueError(f"ACL table link must be pty or tcp, not {link!r}")
        t.update(driver="acl", port=ep["table_acl_pty"] if link == "pty" else ep["table_acl_tcp"],
                 timeout_s=REPLY_TIMEOUT_S)
    elif table == "modbus":
        if link == "tcp":
            host, port = ep["table_modbus_tcp"].rsplit(":", 1)
            t.update(driver="modbus", transport="tcp", host=host, tcp_port=int(port))
        elif link == "rtu":
            t.update(driver="modbus", transport="rtu", port=ep["table_modbus_rtu"], baudrate=hw.rtu_baudrate)
        else:
            raise ValueError(f"Modbus table link must be tcp or rtu, not {link!r}")
        t.update(unit_id=hw.modbus_unit_id, word_order=hw.modbus_word_order, timeout_s=REPLY_TIMEOUT_S)
    else:
        raise ValueError(f"unknown table driver {table!r}")
    i = _keep(i_in)
    proto = getattr(hw, "imu_protocol", "xsens")
    i.update(driver=proto, port=ep[f"imu_{proto}_pty"], baudrate=hw.imu_baudrate, **(imu_options or {}))
    if proto == "frame":
        i["frame"] = copy.deepcopy(hw.imu_frame)
    p = {"driver": "novatel", "port": ep["gnss_novatel_pty"]} if pulses == "novatel" else {"driver": "none"}
    d.update(clock="scaled", speed=float(hw.speed), table=t, imu=i, pulses=p)
    c_in = d.get("chamber") or {}
    c = {k: v for k, v in c_in.items() if k in ("safe_c", "band_c", "sim")}
    if chamber == "watlow-rtu":
        c.update(driver="watlow", transport="rtu", port=ep["chamber_watlow_rtu"], baudrate=hw.rtu_baudrate,
                 timeout_s=REPLY_TIMEOUT_S)
    elif chamber == "watlow-tcp":
        host, port = ep["chamber_watlow_tcp"].rsplit(":", 1)
        c.update(driver="watlow", transport="tcp", host=host, tcp_port=int(port), timeout_s=REPLY_TIMEOUT_S)
    elif chamber == "scpi":
        c.update(driver="scpi", resource=ep["chamber_scpi_visa"], model="generic", timeout_s=REPLY_TIMEOUT_S)
    elif chamber is None:
        c = {"driver": "none"}
    else:
        raise ValueError(f"chamber link must be watlow-rtu, watlow-tcp or scpi, not {chamber!r}")
    if chamber is None:
        d.pop("chamber", None)
    else:
        d["chamber"] = c
    imu_name = {"xsens": "Xsens", "vectornav": "VectorNav", "frame": "declarative-frame"}[proto]
    d["rig"] = f"wired rig on emulated hardware ({table} table over {link}, {imu_name} IMU, {pulses} pulses)"
    return d


def write_wire_config(path: str | Path, base: dict[str, Any], hw, **kw: Any) -> Path:
    """Write :func:`wire_config` to ``path`` (YAML, with a header comment); returns the path."""
    path = Path(path)
    d = wire_config(base, hw, **kw)
    header = ("# Generated by `rigctl sim up`: every device over the wire to the emulated hardware.\n"
              "# Valid while that emulator runs (pty symlinks in "
              f"{hw.link_dir}). Speed {hw.speed:g}x.\n")
    path.write_text(header + yaml.safe_dump(d, sort_keys=False), encoding="utf-8")
    return path
