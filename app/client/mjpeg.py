"""Reading a `multipart/x-mixed-replace` MJPEG body (the cameras' stream): each part's head,
then its `Content-Length` bytes of JPEG. Sans-IO: chunks in, JPEGs out."""

from __future__ import annotations

from collections.abc import AsyncIterator

__all__ = ["MAX_PART_BYTES", "mjpeg_parts"]

#: Largest part accepted, bytes (a 4K JPEG is a few MB): a broken stream cannot grow the buffer.
MAX_PART_BYTES = 32 * 1024 * 1024


async def mjpeg_parts(chunks: AsyncIterator[bytes]) -> AsyncIterator[bytes]:
    """The JPEG of each part of an MJPEG body, as it completes."""
    buf = b""
    async for chunk in chunks:
        buf += chunk
        while True:
            end = buf.find(b"\r\n\r\n")
            if end < 0:
                if len(buf) > 65536:
                    raise ValueError("an MJPEG part head over 64 KiB")
                break
            length = None
            for line in buf[:end].split(b"\r\n"):
                name, _, value = line.partition(b":")
                if name.strip().lower() == b"content-length":
                    length = int(value.strip())
            if length is None or not 0 <= length <= MAX_PART_BYTES:
                raise ValueError("an MJPEG part without a valid Content-Length")
            start = end + 4
            if len(buf) < start + length:
                break
            yield buf[start:start + length]
            buf = buf[start + length:].lstrip(b"\r\n")
