"""Socket steps of the PCIC reader that stay responsive to a stop request: connect, fill a buffer, skip bytes.

Each waits in slices of ``poll_s`` so ``close()`` ends the reader within one slice, never
after a whole connect or stall timeout.
"""

from __future__ import annotations

import errno
import os
import selectors
import socket
import threading
import time

from cellcal.devices.errors import DeviceTimeoutError


def connect(host: str, port: int, timeout_s: float, stop: threading.Event, poll_s: float) -> socket.socket:
    """A connected TCP socket (TCP_NODELAY, timeout ``poll_s``), within ``timeout_s``.

    Raises:
        OSError: Refused, unreachable, timed out (``TimeoutError``) or ``stop`` set.
    """
    deadline = time.monotonic() + timeout_s
    family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setblocking(False)
        err = sock.connect_ex(addr)
        if err not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
            raise OSError(err, os.strerror(err))
        with selectors.DefaultSelector() as sel:
            sel.register(sock, selectors.EVENT_WRITE)
            while not sel.select(min(poll_s, max(deadline - time.monotonic(), 0.0))):
                if stop.is_set():
                    raise OSError("closing")
                if time.monotonic() >= deadline:
                    raise TimeoutError(f"connect timed out after {timeout_s:g} s")
        err = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if err:
            raise OSError(err, os.strerror(err))
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(poll_s)
        return sock
    except BaseException:
        sock.close()
        raise


class Receiver:
    """Reads whole messages from a socket whose timeout is the poll slice.

    Args:
        stop: Set to abandon a read (raises ``OSError("closing")``).
        stall_s: A message that makes no progress for this long raises :class:`DeviceTimeoutError`.
    """

    def __init__(self, stop: threading.Event, stall_s: float) -> None:
        self.stop = stop
        self.stall_s = stall_s
        self._scratch = bytearray(64 * 1024)

    def fill(self, sock: socket.socket, view: memoryview, *, at_boundary: bool, stream_pos: int) -> bool:
        """Fill ``view``; False if nothing arrived at a message boundary (idle).

        Raises:
            DeviceTimeoutError: No progress for ``stall_s`` mid-message.
            EOFError: The peer closed the connection.
            OSError: The link failed or ``stop`` was set.
        """
        got = 0
        last_progress = time.monotonic()
        while got < len(view):
            if self.stop.is_set():
                raise OSError("closing")
            try:
                n = sock.recv_into(view[got:])
            except TimeoutError:
                if at_boundary and got == 0:
                    return False
                if time.monotonic() - last_progress > self.stall_s:
                    raise DeviceTimeoutError(f"stalled mid-message for {self.stall_s:g} s at stream offset "
                                     f"{stream_pos + got}") from None
                continue
            if n == 0:
                raise EOFError
            got += n
            last_progress = time.monotonic()
            at_boundary = False
        return True

    def skip(self, sock: socket.socket, length: int, keep: int, stream_pos: int) -> tuple[bytes, bytes]:
        """Read and discard ``length`` bytes through a fixed 64 KiB buffer.

        Returns:
            The first ``keep`` bytes and the last 2 bytes.
        """
        head = bytearray()
        tail = b""
        done = 0
        while done < length:
            n = min(len(self._scratch), length - done)
            view = memoryview(self._scratch)[:n]
            self.fill(sock, view, at_boundary=False, stream_pos=stream_pos + done)
            if len(head) < keep:
                head += view[:keep - len(head)]
            tail = (tail + bytes(view[-2:]))[-2:]
            done += n
        return bytes(head), tail
