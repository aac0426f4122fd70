"""dragd.client (asyncio) against the real control server (dragd/server.py) with a command table."""

import asyncio

import pytest

from dragd.client import Client, CommandError, DaemonUnavailable
from dragd.server import CommandTable, ControlServer

pytestmark = pytest.mark.unit


def test_client_calls_concurrently_on_one_connection(tmp_path):
    table = CommandTable()
    state = {"mode": "idle"}

    @table.command("status")
    async def status():
        return {"mode": state["mode"]}

    @table.command("mode")
    async def mode(mode: str):
        if mode not in ("hold", "drag", "idle"):
            raise ValueError(f"mode: expected idle, hold or drag, got {mode!r}")
        await asyncio.sleep(0.05)
        state["mode"] = mode
        return {"mode": mode}

    async def handler(request):
        try:
            return await table(request)
        except ValueError as exc:
            from dragd.protocol import ControlError
            raise ControlError(str(exc)) from None

    async def run():
        path = tmp_path / "d.sock"
        async with ControlServer(path, handler):
            async with Client(path, timeout_s=5) as d:
                a, b = await asyncio.gather(d.mode("drag"), d.status())  # answered by id, either order
                assert a == {"ok": True, "mode": "drag", "id": 1} and b["ok"] and b["id"] == 2
                assert (await d.status())["mode"] == "drag"
                with pytest.raises(CommandError, match="expected idle, hold or drag"):
                    await d.mode("fly")
                with pytest.raises(CommandError, match="unknown cmd 'nope'"):
                    await d.call("nope")
                with pytest.raises(CommandError, match="unknown field"):
                    await d.call("status", verbose=1)
        with pytest.raises(DaemonUnavailable, match="no dragd daemon answers"):
            await Client(path).connect()

    asyncio.run(run())
