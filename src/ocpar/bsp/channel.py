"""A blocking socket channel between the coordinator and one worker process: pickled messages
(protocol 5, NumPy buffers out of band) over plain TCP or TLS, answered by a thread of the
worker that runs each request's function and sends back its value.

Why: a Dask comm round trip crosses four threads (the coordinator's, the client's event loop,
the worker's event loop and its task thread), each wake-up costing ~0.1–1 ms on a busy
machine; here the coordinator's thread writes to the socket and the worker's channel thread
reads it (:mod:`ocpar.bsp.dask`, ``dispatch="direct"``; ``scripts/dask_overhead.py``
measures both).

A message is a prefix (``!QQ``: the frame count and the length of the rest) followed by one
``!Q`` length per frame and the frames: the pickle stream first, then its out-of-band buffers,
each at an :data:`ALIGN`-byte boundary; a receiver reads it in two system calls, the prefix
and the rest. NumPy arrays (C-contiguous,
of a plain dtype) are pickled as their dtype's string, their shape and their data out of band
(:func:`encode`): ~2x cheaper on each side than NumPy's own reduction, the same bits. A
request is ``(function, args)``; a reply is ``(True, value)`` or ``(False, exception)``. The
server runs requests one at a time under :data:`SOLVE_LOCK`, which the worker's other ways into
the solvers take too, so a process still makes one solver call at a time.
"""

from __future__ import annotations

import copyreg
import dataclasses
import io
import pickle
import socket
import ssl
import struct
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from ocpar.bsp.backend import UnreadableRequest

#: One solver call at a time per worker process: held while a request runs (and by the Dask
#: paths that run chunks in the worker's task thread, see :mod:`ocpar.bsp.dask_worker`).
SOLVE_LOCK = threading.Lock()

_PREFIX = struct.Struct("!QQ")

#: Out-of-band buffers start at multiples of this many bytes in a message's body, which a
#: receiver reads into memory aligned as ``malloc``'s (16 bytes): an array read from the
#: channel is aligned like a fresh one. NumPy reduces unaligned arrays in buffered pieces,
#: in another order: a float64 sum can differ in its last bit.
ALIGN = 16

class ChannelClosed(ConnectionError):
    """The peer closed the channel (e.g. its process is gone)."""


def unreadable(exc: Exception) -> UnreadableRequest:
    """The one-line :class:`UnreadableRequest` of ``exc``, raised unpickling a request on
    this host."""
    host = socket.gethostname()
    if isinstance(exc, ModuleNotFoundError) and exc.name:
        return UnreadableRequest(
            f"a worker on {host} cannot import module {exc.name!r}, which the run's tasks "
            "need: make it importable on every worker (an installed package, PYTHONPATH in "
            "the workers' environment, or an upload; docs/user-problems.md)")
    return UnreadableRequest(f"a worker on {host} cannot read the run's tasks "
                             f"({type(exc).__name__}: {exc}): is the same code installed "
                             "there?")


#: The dtype kinds :func:`_reduce_array` sends as raw data: booleans, integers, floats, complex.
_PLAIN_KINDS = frozenset("biufc")


def _array(data: pickle.PickleBuffer, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
    """The array that :func:`_reduce_array` reduced: a view of ``data``."""
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def _reduce_array(array: np.ndarray) -> tuple[Any, ...]:
    """``array`` as its data (a buffer, out of band) with its dtype's string and its shape,
    for C-contiguous arrays of booleans or numbers; NumPy's own reduction for the others
    (object, structured, string, date dtypes; non-contiguous or Fortran-ordered arrays)."""
    if array.dtype.kind not in _PLAIN_KINDS or not array.flags.c_contiguous:
        return array.__reduce_ex__(5)
    return _array, (pickle.PickleBuffer(array), array.dtype.str, array.shape)


#: The reductions a message's pickler uses: copyreg's, and :func:`_reduce_array` for arrays.
_DISPATCH = {**copyreg.dispatch_table, np.ndarray: _reduce_array}


@dataclasses.dataclass(frozen=True)
class Message:
    """An object pickled for the channel (:func:`encode`): ``parts`` to write one after the
    other, ``size`` bytes in all."""

    parts: tuple[bytes | memoryview, ...]
    size: int


def _starts(lengths: list[int] | tuple[int, ...]) -> list[int]:
    """Where each frame of a message's body starts (the body: the frames' lengths, then the
    frames): the pickle stream right after the lengths, each buffer at the next multiple of
    :data:`ALIGN` bytes. Both ends compute it from the lengths alone."""
    starts, end = [], 8 * len(lengths)
    for k, length in enumerate(lengths):
        start = end if k == 0 else -(-end // ALIGN) * ALIGN
        starts.append(start)
        end = start + length
    return starts


def encode(obj: Any) -> Message:
    """``obj`` pickled (protocol 5, out-of-band buffers, arrays as :func:`_reduce_array`
    makes them) as one message (module docstring)."""
    buffers: list[pickle.PickleBuffer] = []
    stream = io.BytesIO()
    pickler = pickle.Pickler(stream, protocol=5, buffer_callback=buffers.append)
    pickler.dispatch_table = _DISPATCH
    pickler.dump(obj)
    frames = [stream.getbuffer(), *(b.raw() for b in buffers)]
    lengths = [f.nbytes for f in frames]
    starts = _starts(lengths)
    rest = starts[-1] + lengths[-1]
    parts: list[bytes | memoryview] = [
        struct.pack(f"!QQ{len(frames)}Q", len(frames), rest, *lengths)]
    end = 8 * len(frames)
    for start, frame in zip(starts, frames, strict=True):
        if start > end:
            parts.append(bytes(start - end))  # padding: the next buffer starts aligned
        parts.append(frame)
        end = start + frame.nbytes
    return Message(parts=tuple(parts), size=_PREFIX.size + rest)


def send_encoded(sock: socket.socket, message: Message) -> int:
    """Write ``message`` (:func:`encode`); return its size (bytes, header included)."""
    if isinstance(sock, ssl.SSLSocket):  # no scatter-gather over TLS
        for part in message.parts:
            sock.sendall(part)
        return message.size
    sent = sock.sendmsg(message.parts)  # one system call for a whole small message
    if sent < message.size:
        sock.sendall(memoryview(b"".join(message.parts))[sent:])
    return message.size


def send_message(sock: socket.socket, obj: Any) -> int:
    """Send ``obj`` as one message (:func:`encode`); return the message's length (bytes,
    header included)."""
    return send_encoded(sock, encode(obj))


def _recv_exact(sock: socket.socket, n: int) -> bytearray:
    buf = bytearray(n)
    view, got = memoryview(buf), 0
    while got < n:
        k = sock.recv_into(view[got:], n - got)
        if k == 0:
            raise ChannelClosed("the channel's peer closed the connection")
        got += k
    return buf


def receive_message(sock: socket.socket) -> tuple[Any, int]:
    """Receive one message sent by :func:`send_message`: its object, unpickled, and its
    length (bytes, header included). The whole message is read before it is unpickled, so an
    object that does not unpickle (its exception raised) leaves the channel usable."""
    count, rest = _PREFIX.unpack(_recv_exact(sock, _PREFIX.size))
    body = memoryview(_recv_exact(sock, rest))  # the lengths and every frame in one read
    lengths = struct.unpack_from(f"!{count}Q", body)
    frames = [body[start:start + n] for start, n in zip(_starts(lengths), lengths, strict=True)]
    return pickle.loads(frames[0], buffers=frames[1:]), _PREFIX.size + rest


class ChannelServer:
    """Listens on ``host`` (an ephemeral port; every interface if ``host`` is not one of this
    machine's) in a daemon thread; each connection gets a
    thread that answers its requests in order (module docstring). ``ssl_context``: a server
    context (e.g. the Dask worker's, which requires the client's certificate) or None."""

    def __init__(self, host: str, ssl_context: ssl.SSLContext | None = None) -> None:
        try:
            self._listener = socket.create_server((host, 0))
        except OSError:  # e.g. a contact address behind NAT: listen on every interface
            self._listener = socket.create_server(("", 0))
        self._ssl_context = ssl_context
        #: (host, port) to connect to: ``host`` as given, the port the system chose.
        self.address: tuple[str, int] = (host, self._listener.getsockname()[1])
        threading.Thread(target=self._accept, name="ocpar-channel", daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                sock, _ = self._listener.accept()
            except OSError:  # closed
                return
            threading.Thread(target=self._serve, args=(sock,), name="ocpar-channel-conn",
                             daemon=True).start()

    def _serve(self, sock: socket.socket) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            if self._ssl_context is not None:
                sock = self._ssl_context.wrap_socket(sock, server_side=True)
            while True:
                try:
                    (function, args), _ = receive_message(sock)
                except (OSError, EOFError):
                    raise
                except Exception as exc:  # e.g. a user's module missing on this worker
                    send_message(sock, (False, unreadable(exc)))
                    continue
                with SOLVE_LOCK:
                    try:
                        reply: tuple[bool, Any] = (True, function(*args))
                    except Exception as exc:  # the coordinator re-raises it
                        reply = (False, exc)
                try:
                    send_message(sock, reply)
                except (pickle.PicklingError, TypeError, AttributeError) as exc:
                    send_message(sock, (False, RuntimeError(f"unpicklable reply: {exc!r}")))
        except (OSError, EOFError):  # the coordinator went away (ChannelClosed included)
            pass
        finally:
            sock.close()

    def close(self) -> None:
        """Stop accepting connections (open ones end when their coordinator closes them)."""
        self._listener.close()


class Channel:
    """The coordinator's end: a connection to one :class:`ChannelServer`. :meth:`send` a
    request, later :meth:`receive` its reply (so requests to several workers overlap)."""

    def __init__(self, address: tuple[str, int], ssl_context: ssl.SSLContext | None = None,
                 timeout_s: float = 10.0) -> None:
        sock = socket.create_connection(address, timeout=timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if ssl_context is not None:
            sock = ssl_context.wrap_socket(sock)
        self._sock = sock
        #: Length (bytes) of the last request sent and of the last reply received.
        self.sent_bytes = self.received_bytes = 0

    @staticmethod
    def request(function: Callable[..., Any], *args: Any) -> Message:
        """The request to run ``function(*args)``, encoded (for :meth:`send_request`)."""
        return encode((function, args))

    def send(self, function: Callable[..., Any], *args: Any) -> None:
        """Ask the worker to run ``function(*args)`` (``function`` importable there)."""
        self.send_request(self.request(function, *args))

    def send_request(self, request: Message) -> None:
        """Send a request made by :meth:`request` (several channels' requests encoded first
        go out back to back)."""
        self._sock.settimeout(None)
        self.sent_bytes = send_encoded(self._sock, request)

    def receive(self, timeout_s: float | None = None) -> Any:
        """The value of the last request sent, or its exception raised here; ``socket.timeout``
        after ``timeout_s``, :class:`ChannelClosed`/``OSError`` if the worker is gone."""
        self._sock.settimeout(timeout_s)
        (ok, value), self.received_bytes = receive_message(self._sock)
        if not ok:
            raise value
        return value

    def buffered(self) -> bool:
        """Whether a reply's bytes are read from the socket already (TLS's buffer), so that
        waiting for the socket to be readable would not see them."""
        return isinstance(self._sock, ssl.SSLSocket) and self._sock.pending() > 0

    def fileno(self) -> int:
        """The socket's file descriptor (to wait on several channels' replies, ``selectors``)."""
        return self._sock.fileno()

    def close(self) -> None:
        self._sock.close()
