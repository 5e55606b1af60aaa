"""A gzip stream inflated by a worker thread while the caller decodes what has already arrived.

Inflating a gzip member is sequential, but the caller's decoding of the first bytes need not wait for
the last: :class:`BackgroundGunzip` inflates into one preallocated ``uint8`` buffer in a worker thread
(ISA-L's inflate releases the GIL) and :meth:`BackgroundGunzip.wait` blocks until a prefix of the
buffer is filled. So reading an SPZ file costs about the longer of inflating and decoding, not their sum
(on a machine with a free core).

Errors found by the worker (a broken stream, a CRC mismatch, a stream that ends early, bytes after it)
come back as :class:`~seggaussian.io.splat_common.SplatFormatError` from ``wait`` or ``finish``, whose
messages name the file and the format. ``finish`` must be called (a ``with`` block does it): it joins the
thread and reports an error the caller's waits did not reach, such as a bad CRC at the end.
"""

from __future__ import annotations

import threading

import numpy as np
from isal import isal_zlib

from seggaussian.io.splat_common import SplatFormatError

__all__ = ["GZIP_WBITS", "BackgroundGunzip"]

#: ``wbits`` of a gzip-wrapped deflate stream (zlib's convention, also ISA-L's).
GZIP_WBITS = 16 + 15
#: Compressed bytes fed to the inflater at a time, and inflated bytes taken out at a time: small enough
#: that the reader starts early, large enough that the per-call overhead is negligible.
IN_CHUNK = 1 << 20
OUT_CHUNK = 1 << 22


class BackgroundGunzip:
    """Inflate ``data`` (one gzip member) into ``buffer[:size]`` in a worker thread.

    Bytes of the payload beyond ``size`` are inflated (the CRC covers them) but not kept; ``total`` counts
    all of them once the thread is done.
    """

    def __init__(self, data: bytes, size: int, where: str) -> None:
        self.buffer = np.empty(size, np.uint8)
        self.filled = 0
        self.total = 0
        self._where = where
        self._error: str | None = None
        self._done = False
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._run, args=(data,), name="gunzip", daemon=True)
        self._thread.start()

    def _store(self, piece: bytes) -> None:
        keep = min(len(piece), self.buffer.shape[0] - self.filled)
        if keep > 0:
            self.buffer[self.filled: self.filled + keep] = np.frombuffer(piece, np.uint8, keep)
        with self._cond:
            self.filled += max(keep, 0)
            self.total += len(piece)
            self._cond.notify_all()

    def _run(self, data: bytes) -> None:
        inflater = isal_zlib.decompressobj(GZIP_WBITS)
        view = memoryview(data)
        error = None
        try:
            for start in range(0, len(data), IN_CHUNK):
                pending = view[start: start + IN_CHUNK]
                while pending and not inflater.eof:
                    self._store(inflater.decompress(pending, OUT_CHUNK))
                    pending = inflater.unconsumed_tail
                if inflater.eof:
                    break
            if not inflater.eof:
                error = f"truncated gzip stream (no end of stream after {len(data)} bytes)"
            elif inflater.unused_data:
                error = f"{len(inflater.unused_data)} bytes after the gzip stream"
        except isal_zlib.error as exc:
            error = f"broken gzip stream ({exc})"
        with self._cond:
            self._error = error
            self._done = True
            self._cond.notify_all()

    def wait(self, end: int, truncated: str) -> None:
        """Block until ``buffer[:end]`` is filled; ``SplatFormatError`` (``truncated`` when the stream
        ended too early, else the worker's error) when it never will be."""
        with self._cond:
            self._cond.wait_for(lambda: self.filled >= end or self._done)
            if self.filled >= end:
                return
            error = self._error
        raise SplatFormatError(f"{self._where}: {error or truncated}")

    def finish(self) -> None:
        """Join the worker; ``SplatFormatError`` for an error found after the last wait."""
        self._thread.join()
        if self._error:
            raise SplatFormatError(f"{self._where}: {self._error}")

    def __enter__(self) -> "BackgroundGunzip":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.finish()
        else:
            self._thread.join()      # the caller's error wins; never leave the thread behind
