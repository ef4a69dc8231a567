"""drvs.gateway.guard: a head that does not arrive in time closes its connection, a client address
gets so many connections and no more, and a normal client is answered meanwhile."""

import asyncio

from aiohttp import web

from drvs.gateway.guard import GuardedRunner

HEAD_TIMEOUT = 0.3
PER_ADDRESS = 4


async def _hello(request: web.Request) -> web.Response:
    return web.Response(text='hello')


async def _serve():
    app = web.Application()
    app.router.add_get('/', _hello)
    runner = GuardedRunner(app, head_timeout=HEAD_TIMEOUT, max_per_address=PER_ADDRESS, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, '127.0.0.1', 0)
    await site.start()
    port = site._server.sockets[0].getsockname()[1]
    return runner, port


async def _get(port: int) -> bytes:
    reader, writer = await asyncio.open_connection('127.0.0.1', port)
    writer.write(b'GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n')
    answer = await asyncio.wait_for(reader.read(), 5)
    writer.close()
    return answer


async def _closed(reader: asyncio.StreamReader, seconds: float) -> bool:
    """Whether the server closed the connection within ``seconds``."""
    try:
        return await asyncio.wait_for(reader.read(), seconds) == b''
    except TimeoutError:
        return False


def test_a_slow_head_is_cut_off_and_others_are_answered_meanwhile():
    async def main():
        runner, port = await _serve()
        try:
            slow = [await asyncio.open_connection('127.0.0.1', port) for _ in range(2)]
            for _, writer in slow:
                writer.write(b'GET / HT')  # and no more
            answer = await _get(port)  # while the slow ones are open
            assert answer.startswith(b'HTTP/1.1 200') and answer.endswith(b'hello')
            assert len(runner.peers.open) == 1 and runner.peers.open['127.0.0.1'] == 2
            for reader, writer in slow:
                assert await _closed(reader, 20 * HEAD_TIMEOUT)
                writer.close()
            await asyncio.sleep(0)
            assert runner.peers.open == {}
        finally:
            await runner.cleanup()

    asyncio.run(main())


def test_a_complete_head_is_not_cut_off():
    async def main():
        runner, port = await _serve()
        try:
            reader, writer = await asyncio.open_connection('127.0.0.1', port)
            writer.write(b'GET / HTTP/1.1\r\nHost: x\r\n\r\n')
            assert (await reader.readuntil(b'hello')).startswith(b'HTTP/1.1 200')
            assert not await _closed(reader, 3 * HEAD_TIMEOUT)  # kept alive past the head's deadline
            writer.close()
        finally:
            await runner.cleanup()

    asyncio.run(main())


def test_one_address_gets_so_many_connections_and_no_more():
    async def main():
        runner, port = await _serve()
        try:
            held = [await asyncio.open_connection('127.0.0.1', port) for _ in range(PER_ADDRESS)]
            await asyncio.sleep(0.05)
            extra, writer = await asyncio.open_connection('127.0.0.1', port)
            assert await _closed(extra, HEAD_TIMEOUT / 2)  # at once, not at the head's deadline
            writer.close()
            for _, writer in held:
                writer.close()
            for reader, _ in held:
                await _closed(reader, 5)
            assert (await _get(port)).endswith(b'hello')  # places freed
        finally:
            await runner.cleanup()

    asyncio.run(main())
