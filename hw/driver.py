"""The base of every serial driver: declared exchanges, connection set-up, retried operations.

A driver subclasses ``LineInstrument``, sets ``protocol`` (its declared ``Protocol``), implements
``connect()`` (identify the instrument and set it up; run again after any failure, so a port
that came back or an instrument that was reset is set up anew) and, when the instrument keeps an
error queue, ``pending_error()`` (asked after a timeout or a bad reply, so the error reported is
the instrument's own code and text). Each interface method runs its exchanges inside
``operation(...)``, which retries with bounded back-off (hw/retry.py).
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, TypeVar

from deltatwin.hw.protocol import InstrumentRejected, PortLost, Protocol, ReplyError, SerialLine
from deltatwin.hw.retry import RetryPolicy, retry
from deltatwin.twin.instruments.interface import InstrumentError, InstrumentTimeout

log = logging.getLogger(__name__)
T = TypeVar("T")


class LineInstrument:
    protocol: Protocol
    identity_prefix: str | None = None   # generic protocols: what ``identify`` must start with

    def __init__(self, line: SerialLine, *, name: str, retry_policy: RetryPolicy = RetryPolicy()):
        self.line, self.name, self.retry_policy = line, name, retry_policy
        self._connected = False

    # ---- one exchange (no retry)
    def ask(self, command: str, timeout_s: float | None = None, **values) -> dict[str, Any]:
        """Send ``command`` with ``values`` and return the parsed reply fields."""
        self.line.write_line(self.protocol.request(command, **values))
        if self.protocol.commands[command].reply is None:
            return {}
        reply = self.line.read_line(timeout_s)
        return self.protocol.parse_reply(command, reply, values, self.name)

    # ---- hooks
    def connect(self) -> None:
        """Identify and set up the instrument (after opening and after every failure). The
        default checks the generic protocols' identity against ``identity_prefix``."""
        if self.identity_prefix is None:
            return
        identity = self.ask("identify")["identity"]
        if not identity.startswith(self.identity_prefix):
            raise InstrumentRejected(self.name, f"{self.line.url} identifies as {identity!r}, "
                                                f"not a {self.identity_prefix}")

    def pending_error(self) -> InstrumentError | None:
        """The instrument's own error, if it keeps one, after a failed exchange."""
        return None

    # ---- retried operation
    def operation(self, what: str, action: Callable[[], T], timeout_s: float | None) -> T:
        def attempt() -> T:
            try:
                if not self._connected:
                    self.connect()
                    self._connected = True
                return action()
            except (InstrumentTimeout, ReplyError) as exc:
                self._connected = False
                own = self._pending_error_or_none()
                if own is not None:
                    raise own from exc
                raise
            except InstrumentError:
                self._connected = False
                raise

        return retry(attempt, instrument=self.name, what=what, policy=self.retry_policy,
                     timeout_s=timeout_s, recover=self._recover)

    def _pending_error_or_none(self) -> InstrumentError | None:
        try:
            self.line.discard_input()
            return self.pending_error()
        except InstrumentError as exc:   # the error query failed too: keep the first error
            log.debug("%s: error query failed: %s", self.name, exc)
            return None

    def _recover(self, error: InstrumentError) -> None:
        if isinstance(error, PortLost):
            self.line.close()            # reopened by the next exchange
            return
        dropped = self.line.discard_input()
        if dropped:
            log.info("%s: discarded %d stale byte(s) after a fault: %r", self.name,
                     len(dropped), dropped[:80])

    def close(self) -> None:
        self.line.close()
