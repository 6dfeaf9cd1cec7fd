"""A bounded aiohttp server in its own process, for the slowloris test's memory figures.

`python -m tests.api.limits_server HEADER_TIMEOUT_S [unbounded]` prints its port, serves
GET / and POST /echo until stdin closes. `unbounded` serves the same app with aiohttp's
plain AppRunner/TCPSite (the control: shows what the bounds change).
"""

from __future__ import annotations

import asyncio
import sys

from aiohttp import web

from softplc.api.limits import HttpBounds, HttpLimits


async def _hello(request: web.Request) -> web.Response:
    return web.Response(text="ok")


async def _echo(request: web.Request) -> web.Response:
    return web.Response(body=await request.read())


async def main(header_timeout_s: float, bounded: bool) -> None:
    app = web.Application()
    app.router.add_get("/", _hello)
    app.router.add_post("/echo", _echo)
    if bounded:
        bounds = HttpBounds(HttpLimits(header_timeout_s=header_timeout_s))
        runner = bounds.runner(app, access_log=None)
        await runner.setup()
        site = bounds.site(runner, "127.0.0.1", 0)
    else:
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    print(runner.addresses[0][1], flush=True)
    await asyncio.to_thread(sys.stdin.read)  # until the test closes our stdin
    await runner.cleanup()


if __name__ == "__main__":
    asyncio.run(main(float(sys.argv[1]), bounded=sys.argv[2:] != ["unbounded"]))
