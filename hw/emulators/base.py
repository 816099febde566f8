"""What every emulator shares: the link (pseudo-terminal or TCP), the serving thread, the
backing instruments (any ``InstrumentSet``, called under one lock, optionally paced in real
time) and fault injection.

An emulator parses each request with its instrument's declared ``Protocol`` (the same table the
driver uses), turns it into calls on the backing ``InstrumentSet`` and formats the reply from the
table. Subclasses implement ``handle(command, values)`` (-> reply line or None), ``unknown(line)``
(a request that is no declared command) and ``fail(error, request)`` (how this instrument reports an
error: an error reply, an error queue, an error register).

Links: ``PtyLink`` serves on a pseudo-terminal (``os.openpty``) and publishes it as a SYMLINK
(``<directory>/<name>`` -> ``/dev/pts/N``): that path goes to the ports file, so when the port
"vanishes" (pty closed) and "comes back" (a new pty: a new /dev/pts/N), the symlink is re-pointed
and a driver reopening the same path finds it again. ``TcpLink`` serves ``socket://127.0.0.1:P``
(one client at a time), and comes back on the same port.

Faults (``inject``), consumed one per request (``count`` requests, or every request until
``clear_faults`` when ``count`` is None), starting ``after`` requests from now (so that a test can
place a fault in the middle of a campaign); all but ``error_code`` only affect requests that the
instrument answers:
  ``no_reply``      the request is lost: not executed, no reply (the driver times out);
  ``garbled``       executed; a third of the reply's bytes replaced by bytes 0x80-0xFF;
  ``truncated``     executed; only the first half of the reply, without terminator;
  ``dropped_bytes`` executed; a burst of 1-3 bytes lost from the reply (terminator kept);
  ``xoff``          executed; a stray XOFF byte (0x13) inserted in the reply;
  ``error_code``    not executed; the instrument reports error ``code`` (``reason``) its way;
  ``vanish``        the port disappears for ``down_s`` seconds: at once, or with ``after`` at
                    that request (which is lost);
an emulator may add faults of its own instrument (``instrument_faults``; its ``serve`` sees the
fault applying to the present request as ``self.active_fault``).
Random choices (which bytes) come from the emulator's seeded ``numpy.random.Generator``.
"""
from __future__ import annotations

import logging
import os
import select
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deltatwin.hw.protocol import Protocol, terminator_bytes
from deltatwin.twin.instruments.interface import InstrumentError, InstrumentSet

log = logging.getLogger(__name__)

FAULTS = ("no_reply", "garbled", "truncated", "dropped_bytes", "xoff", "error_code", "vanish")


class BackingLab:
    """The ``InstrumentSet`` behind every emulator of one laboratory. ``call`` serialises the
    calls (one lock) and, when ``realtime``, then sleeps until the wall clock has caught up with
    the backing clock (so a simulated clock is paced in real time)."""

    def __init__(self, instruments: InstrumentSet, realtime: bool = False):
        self.instruments, self.realtime = instruments, realtime
        self._lock = threading.RLock()
        self._t0_wall = time.monotonic()
        self._t0_sim = instruments.clock.now()

    def call(self, fn, *args, **kw):
        with self._lock:
            result = fn(*args, **kw)
            if self.realtime:
                lag = (self.instruments.clock.now() - self._t0_sim) - (time.monotonic()
                                                                       - self._t0_wall)
                if lag > 0:
                    time.sleep(lag)
            return result


# --------------------------------------------------------------------------- links

class PtyLink:
    """A pseudo-terminal published as the symlink ``directory/name``."""

    def __init__(self, directory: Path, name: str):
        self.path = Path(directory) / name
        self.device = ""
        self._master = self._slave = -1
        self.up()

    @property
    def url(self) -> str:
        return str(self.path)

    def up(self) -> None:
        self._master, self._slave = os.openpty()
        import tty  # POSIX only: emulators serve pseudo-terminals
        tty.setraw(self._slave)          # no echo, no CR/LF translation, 8-bit clean
        os.set_blocking(self._master, False)
        self.device = os.ttyname(self._slave)
        tmp = self.path.with_name(f".{self.path.name}.new")
        if tmp.is_symlink():
            tmp.unlink()
        os.symlink(self.device, tmp)
        os.replace(tmp, self.path)       # atomic re-point

    def down(self) -> None:
        if self.path.is_symlink():
            self.path.unlink()
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    def fileno(self) -> int | None:
        return self._master if self._master >= 0 else None

    def read(self) -> bytes:
        try:
            return os.read(self._master, 4096)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:                  # EIO: no slave open at the moment
            return b""

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._master, view)
            except BlockingIOError:
                select.select([], [self._master], [], 0.1)
                continue
            except OSError:              # closed meanwhile (the port vanished): reply lost
                return
            view = view[n:]


class TcpLink:
    """``socket://127.0.0.1:PORT``, one client at a time; comes back on the same port."""

    def __init__(self, port: int = 0):
        self.port = port
        self.device = ""
        self._server: socket.socket | None = None
        self._client: socket.socket | None = None
        self.up()

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def up(self) -> None:
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(("127.0.0.1", self.port))
        server.listen(1)
        server.setblocking(False)
        self.port = server.getsockname()[1]
        self.device = f"tcp 127.0.0.1:{self.port}"
        self._server = server

    def down(self) -> None:
        for s in (self._client, self._server):
            if s is not None:
                s.close()
        self._client = self._server = None

    def fileno(self) -> int | None:
        if self._client is not None:
            return self._client.fileno()
        return self._server.fileno() if self._server is not None else None

    def read(self) -> bytes:
        if self._client is None:
            try:
                self._client, _ = self._server.accept()
                self._client.setblocking(False)
            except BlockingIOError:
                pass
            return b""
        try:
            data = self._client.recv(4096)
        except BlockingIOError:
            return b""
        except OSError:
            data = b""
        if not data:                     # client went away: wait for the next one
            self._client.close()
            self._client = None
        return data

    def write(self, data: bytes) -> None:
        if self._client is not None:
            try:
                self._client.sendall(data)
            except OSError:
                pass


# --------------------------------------------------------------------------- faults

@dataclass
class Fault:
    kind: str
    count: int | None = 1           # requests affected; None = until cleared
    code: str | int | None = None   # error_code: the instrument's code
    reason: str = "injected fault"
    after: int = 0                  # requests (to which it applies) to let pass first
    down_s: float = 0.5             # vanish: how long the port stays away


# --------------------------------------------------------------------------- the emulator

class LineEmulator:
    """Serves one instrument's protocol on ``link`` from a daemon thread."""
    protocol: Protocol
    default_error_code: str | int = 5
    instrument_faults: tuple[str, ...] = ()
    # longest request line (terminator excluded) the input buffer holds: the LDS1000 manual's
    # 255 characters, used for every emulator; a longer line is discarded and refused
    max_line = 255

    def __init__(self, backing: BackingLab, link, *, name: str, terminator: str | None = None,
                 seed: int = 0):
        self.backing, self.link, self.name = backing, link, name
        self.terminator_name = terminator or self.protocol.terminator
        self.terminator = terminator_bytes(self.terminator_name)
        self.rng = np.random.default_rng(seed)
        self._faults: list[Fault] = []
        self._fault_lock = threading.Lock()
        self._back_at: float | None = None
        self._buffer = bytearray()
        self._overrun = False       # the line being received is too long: drop it to its end
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name=f"emulator-{name}",
                                        daemon=True)
        self.requests = 0      # requests served (for tests and logs)
        self.faults_applied = dict.fromkeys(FAULTS + self.instrument_faults, 0)
        self.active_fault: Fault | None = None   # the fault applying to the request served

    # ---- subclass hooks
    def handle(self, command: str, values: dict) -> str | None:
        raise NotImplementedError

    def unknown(self, line: str) -> str | None:
        raise NotImplementedError

    def fail(self, error: InstrumentError, request: tuple[str, dict] | None) -> str | None:
        """Report ``error`` (raised while serving ``request``, the parsed request or None)."""
        raise NotImplementedError

    def overlong(self) -> str | None:
        """Report a request line longer than ``max_line`` (discarded unread)."""
        raise NotImplementedError

    def parse_request(self, line: str) -> tuple[tuple[str, dict] | None, bool]:
        """(the request parsed as (command, values) or None, whether the instrument answers
        it)."""
        parsed = self.protocol.parse_request(line)
        return parsed, parsed is None or self.protocol.commands[parsed[0]].reply is not None

    # ---- control
    @property
    def url(self) -> str:
        return self.link.url

    def start(self) -> LineEmulator:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.link.down()

    def inject(self, kind: str, count: int | None = 1, *, code=None, reason: str = "injected "
               "fault", down_s: float = 0.5, after: int = 0) -> None:
        known = FAULTS + self.instrument_faults
        if kind not in known:
            raise ValueError(f"{self.name}: unknown fault {kind!r}; known: {known}")
        if after < 0:
            raise ValueError(f"{self.name}: after must be >= 0, got {after}")
        if kind == "vanish" and after == 0:
            with self._fault_lock:
                self._vanish(down_s)
            return
        with self._fault_lock:
            self._faults.append(Fault(kind, 1 if kind == "vanish" else count, code, reason,
                                      after, down_s))

    def _vanish(self, down_s: float) -> None:
        """Take the port away for ``down_s`` seconds (call with the fault lock held)."""
        self.link.down()
        self._buffer.clear()
        self._overrun = False
        self._back_at = time.monotonic() + down_s
        self.faults_applied["vanish"] += 1
        log.info("%s: port vanished for %.2f s", self.name, down_s)

    def clear_faults(self) -> None:
        """Drop the pending faults; a vanished port comes back now."""
        with self._fault_lock:
            self._faults.clear()
            if self._back_at is not None:
                self._back_at = time.monotonic()

    def instrument_fault_applies(self, kind: str, command: str | None) -> bool:
        """Whether this instrument's own fault ``kind`` applies to ``command`` (None: a request
        that is no declared command)."""
        return True

    def _next_fault(self, answers: bool, command: str | None) -> Fault | None:
        """Consume the next fault, if it applies to this request: ``error_code`` applies to any
        request, an instrument fault where ``instrument_fault_applies``, the others only to
        requests that the instrument answers."""
        with self._fault_lock:
            if not self._faults:
                return None
            fault = self._faults[0]
            if fault.kind in self.instrument_faults:
                applies = self.instrument_fault_applies(fault.kind, command)
            else:
                applies = answers or fault.kind == "error_code"
            if not applies:
                return None
            if fault.after > 0:
                fault.after -= 1
                return None
            if fault.kind != "vanish":
                self.faults_applied[fault.kind] += 1
            if fault.count is not None:
                fault.count -= 1
                if fault.count <= 0:
                    self._faults.pop(0)
            return fault

    # ---- serving
    def _serve(self) -> None:
        while not self._stop.is_set():
            with self._fault_lock:
                if self._back_at is not None and time.monotonic() >= self._back_at:
                    self.link.up()
                    self._back_at = None
                    log.info("%s: port back at %s -> %s", self.name, self.link.url,
                             self.link.device)
                fd = self.link.fileno()
            if fd is None:
                time.sleep(0.01)
                continue
            try:
                ready, _, _ = select.select([fd], [], [], 0.05)
            except (OSError, ValueError):   # closed under us by a vanish
                continue
            if not ready:
                continue
            with self._fault_lock:
                if self.link.fileno() != fd:
                    continue
                data = self.link.read()
            if not data:
                continue
            self._buffer += data
            while (end := self._buffer.find(self.terminator)) >= 0:
                line = bytes(self._buffer[:end]).decode("latin-1")
                del self._buffer[:end + len(self.terminator)]
                if self.terminator == b"\n" and line.endswith("\r"):
                    line = line[:-1]                # CR LF: the CR is part of the terminator
                if self._overrun or len(line) > self.max_line:
                    self._overrun = False
                    self._refuse_overlong()
                else:
                    self._answer(line)
            if len(self._buffer) > self.max_line:  # no terminator in sight: bounded buffer
                self._buffer.clear()
                self._overrun = True

    def _refuse_overlong(self) -> None:
        self.requests += 1
        log.info("%s: request line longer than %d characters refused", self.name, self.max_line)
        reply = self.overlong()
        if reply is not None:
            self.link.write(reply.encode("latin-1") + self.terminator)

    def _answer(self, line: str) -> None:
        self.requests += 1
        parsed, answers = self.parse_request(line)
        fault = self._next_fault(answers, None if parsed is None else parsed[0])
        if fault is not None and fault.kind == "no_reply":
            log.info("%s: fault no_reply for %r", self.name, line)
            return
        if fault is not None and fault.kind == "vanish":
            log.info("%s: fault vanish at %r", self.name, line)
            with self._fault_lock:
                self._vanish(fault.down_s)
            return
        self.active_fault = fault if fault is not None and fault.kind in self.instrument_faults \
            else None
        try:
            if fault is not None and fault.kind == "error_code":
                code = self.default_error_code if fault.code is None else fault.code
                log.info("%s: fault error_code %s for %r", self.name, code, line)
                reply = self.fail(InstrumentError(self.name, fault.reason, code), parsed)
            elif parsed is None:
                reply = self.unknown(line)
            else:
                try:
                    reply = self.handle(*parsed)
                except InstrumentError as exc:      # the backing instrument failed
                    reply = self.fail(exc, parsed)
        except Exception:                            # an emulator bug: say so, keep serving
            log.exception("%s: emulator failed on %r", self.name, line)
            return
        if reply is None:
            return
        data = reply.encode("latin-1") + self.terminator
        if fault is not None:
            data = self._corrupt(fault.kind, data)
        self.link.write(data)

    def _corrupt(self, kind: str, data: bytes) -> bytes:
        body = bytearray(data[:-len(self.terminator)])
        n = len(body)
        if kind == "garbled" and n:
            idx = self.rng.choice(n, size=max(1, n // 3), replace=False)
            for i in idx:
                body[i] = int(self.rng.integers(0x80, 0x100))
            return bytes(body) + self.terminator
        if kind == "truncated":
            return bytes(body[:n // 2])
        if kind == "dropped_bytes" and n:
            k = int(self.rng.integers(1, min(3, n) + 1))
            start = int(self.rng.integers(0, n - k + 1))
            del body[start:start + k]
            return bytes(body) + self.terminator
        if kind == "xoff":
            pos = int(self.rng.integers(0, n + 1))
            body[pos:pos] = b"\x13"
            return bytes(body) + self.terminator
        return data


class BackgroundAction:
    """A slow instrument action (a move, a current ramp) run in its own thread so that the
    emulator keeps answering polls while it lasts."""

    def __init__(self):
        self._thread: threading.Thread | None = None
        self._error: InstrumentError | None = None

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, fn, *args) -> None:
        self._error = None

        def run():
            try:
                fn(*args)
            except InstrumentError as exc:
                self._error = exc

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def done(self) -> bool:
        """True when finished; raises (once) the error the action ended with."""
        if self.busy:
            return False
        error, self._error = self._error, None
        if error is not None:
            raise error
        return True
