"""A minimal keep-alive HTTP/1.1 JSON client on asyncio streams, for load generation.

httpx spends about a millisecond of CPU per request; with a hundred simulated clients in one
process on a 2-core machine the load generator, not the server, becomes the bottleneck. This client
does only what the benchmarks need (JSON bodies, Content-Length responses, one connection per
client) and costs a small fraction of that.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from typing import Any
from urllib.parse import urlsplit


class RawHttp:
    """One persistent connection to one server."""

    def __init__(self, base_url: str, headers: dict[str, str] | None = None) -> None:
        parts = urlsplit(base_url)
        self.host = parts.hostname or "127.0.0.1"
        self.port = parts.port or 80
        self.headers = dict(headers or {})
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    async def _connect(self) -> None:
        self._reader, self._writer = await asyncio.open_connection(self.host, self.port)

    async def request(self, method: str, path: str, body: Any = None) -> tuple[int, Any]:
        """Send a request; returns (status, parsed JSON body or None).

        A keep-alive connection the server closed while idle is reopened once; only requests the
        benchmarks may safely repeat (the API's are idempotent) go through here.
        """
        try:
            return await self._send(method, path, body)
        except (asyncio.IncompleteReadError, ConnectionResetError, BrokenPipeError):
            await self.close()
            return await self._send(method, path, body)

    async def _send(self, method: str, path: str, body: Any) -> tuple[int, Any]:
        if self._writer is None:
            await self._connect()
        assert self._reader is not None and self._writer is not None
        payload = b"" if body is None else json.dumps(body).encode()
        lines = [f"{method} {path} HTTP/1.1", f"Host: {self.host}:{self.port}"]
        lines += [f"{name}: {value}" for name, value in self.headers.items()]
        if body is not None:
            lines += ["Content-Type: application/json", f"Content-Length: {len(payload)}"]
        self._writer.write(("\r\n".join(lines) + "\r\n\r\n").encode() + payload)
        head = await self._reader.readuntil(b"\r\n\r\n")
        status_line, *header_lines = head.decode("latin-1").split("\r\n")
        status = int(status_line.split(" ", 2)[1])
        length = 0
        for line in header_lines:
            name, _, value = line.partition(":")
            lowered = name.strip().lower()
            if lowered == "content-length":
                length = int(value)
            elif lowered == "set-cookie":
                cookie = value.strip().split(";", 1)[0]
                existing = self.headers.get("Cookie")
                self.headers["Cookie"] = f"{existing}; {cookie}" if existing else cookie
        raw = await self._reader.readexactly(length) if length else b""
        return status, json.loads(raw) if raw else None

    async def close(self) -> None:
        """Close the connection."""
        if self._writer is not None:
            self._writer.close()
            with contextlib.suppress(ConnectionResetError, BrokenPipeError):
                await self._writer.wait_closed()
            self._writer = None
