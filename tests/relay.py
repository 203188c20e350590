"""A TCP relay that adds a fixed latency in both directions: `python relay.py LISTEN TARGET DELAY_S`.

LISTEN and TARGET are `HOST:PORT`. Every accepted connection is forwarded to TARGET; each chunk
read from one side is written to the other `DELAY_S` seconds after it was read. Each direction
has a queue of (due time, chunk): a reader appends as fast as data arrives, a writer waits for
the head's due time and writes it. Chunks read together are due together, so the relay adds
latency without limiting throughput (a sleep per chunk would serialize them), and order is kept
(due times never decrease). EOF is delayed like data; a reset on either side aborts both.

Once listening it prints `listening HOST:PORT` on stdout (the harness waits for that line).
It runs until killed.
"""

from __future__ import annotations

import asyncio
import sys

CHUNK = 65536


def _split(address: str) -> tuple[str, int]:
    host, _, port = address.rpartition(":")
    return host, int(port)


async def _pump(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, delay_s: float, peers: list[asyncio.StreamWriter]
) -> None:
    """Copy `reader` to `writer`, each chunk `delay_s` after it was read; EOF is forwarded the same way."""
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

    def reset() -> None:
        for peer in peers:  # a reset on one side: the other side is reset too
            peer.transport.abort()

    async def read() -> None:
        try:
            while chunk := await reader.read(CHUNK):
                queue.put_nowait((loop.time() + delay_s, chunk))
        except OSError:
            reset()
        finally:
            queue.put_nowait((loop.time() + delay_s, b""))

    async def write() -> None:
        try:
            while True:
                due, chunk = await queue.get()
                wait = due - loop.time()
                if wait > 0:
                    await asyncio.sleep(wait)
                if writer.is_closing():
                    return
                if not chunk:
                    if writer.can_write_eof():
                        writer.write_eof()
                    return
                writer.write(chunk)
                await writer.drain()
        except OSError:
            reset()

    await asyncio.gather(read(), write())


async def _handle(
    client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter, target: tuple[str, int], delay_s: float
) -> None:
    try:
        upstream_reader, upstream_writer = await asyncio.open_connection(*target)
    except OSError:
        client_writer.transport.abort()
        return
    peers = [client_writer, upstream_writer]
    try:
        await asyncio.gather(
            _pump(client_reader, upstream_writer, delay_s, peers),
            _pump(upstream_reader, client_writer, delay_s, peers),
        )
    finally:
        for peer in peers:
            peer.close()


async def _main(listen: str, target: str, delay_s: float) -> None:
    host, port = _split(listen)
    goal = _split(target)
    server = await asyncio.start_server(
        lambda r, w: _handle(r, w, goal, delay_s), host, port, reuse_address=True, backlog=64
    )
    print(f"listening {host}:{port}", flush=True)
    async with server:
        await server.serve_forever()


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print("usage: relay.py LISTEN_HOST:PORT TARGET_HOST:PORT DELAY_S", file=sys.stderr)
        return 2
    asyncio.run(_main(argv[0], argv[1], float(argv[2])))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
