"""What every emulated Modbus device in sim/ shares: an asyncio loop in a thread that serves one
pymodbus ``SimDevice`` over Modbus TCP (127.0.0.1, OS-picked port) and over Modbus RTU on a pty
null-modem pair, at the same time, and shuts both down.

A device (:class:`rigctl.sim.modbus_server.ModbusTableServer`,
:class:`rigctl.sim.chamber_servers.WatlowF4TServer`) subclasses :class:`ModbusEndpoints`,
calls :meth:`_start_loop` in its ``__init__`` once its registers exist, and implements
:meth:`_device` (the register blocks and the ``action`` callback that is the source of truth).
"""
from __future__ import annotations

import asyncio
import threading
from collections.abc import Coroutine
from typing import Any

from pymodbus.framer import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import SimDevice

from .links import PtyBridge


class ModbusEndpoints:
    """Serve :meth:`_device` on TCP and RTU from one asyncio loop (see the module docstring)."""

    #: thread and pty names (``NAME-loop``, ``NAME-rtu``)
    name = "modbus"
    #: RTU baud rate when ``start_rtu`` is given none
    default_baudrate = 19200

    def _start_loop(self) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name=f"{self.name}-loop",
                                        daemon=True)
        self._thread.start()
        self._servers: list = []
        self._bridges: list[PtyBridge] = []
        self._closed = False

    def _device(self) -> SimDevice:  # pragma: no cover - subclass duty
        raise NotImplementedError

    def _run(self, coro: Coroutine[Any, Any, Any], timeout: float = 10.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout)

    def start_tcp(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Serve Modbus TCP; returns the bound (host, port)."""
        async def go():
            srv = ModbusTcpServer(self._device(), address=(host, port))
            await srv.serve_forever(background=True)
            self._servers.append(srv)
            return srv.transport.sockets[0].getsockname()[:2]
        return self._run(go())

    def start_rtu(self, baudrate: int | None = None, parity: str = "N") -> str:
        """Serve Modbus RTU on one end of a pty null-modem pair; returns the path the client opens."""
        bridge = PtyBridge(name=f"{self.name}-rtu")
        self._bridges.append(bridge)

        async def go():
            srv = ModbusSerialServer(self._device(), framer=FramerType.RTU, port=bridge.path_a,
                                     baudrate=baudrate or self.default_baudrate, parity=parity)
            await srv.serve_forever(background=True)
            self._servers.append(srv)
        self._run(go())
        return bridge.path_b

    async def _shutdown(self) -> None:
        """Runs on the loop at close; a subclass with tasks of its own extends it."""
        for srv in self._servers:
            await srv.shutdown()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._run(self._shutdown())
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=5)
            self._loop.close()
            for b in self._bridges:
                b.close()

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
