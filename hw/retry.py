"""Bounded retry with exponential back-off: the one place where drivers decide to try again.

Every failure is logged (logger ``hw.retry``, WARNING) with the instrument, the operation, the
attempt and the reason; a fault that persists past the last attempt (or the operation's deadline)
raises one clear ``InstrumentError`` (``InstrumentTimeout`` if every attempt timed out) naming
the operation, the number of attempts, the time spent and the last reason. ``InstrumentRejected``
(the instrument refused: retrying cannot help) is raised at once.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from deltatwin.hw.protocol import InstrumentRejected
from deltatwin.twin.instruments.interface import InstrumentError, InstrumentTimeout

log = logging.getLogger(__name__)
T = TypeVar("T")


@dataclass(frozen=True)
class RetryPolicy:
    """``attempts`` in all (>= 1); the wait before attempt k+1 is
    ``min(first_delay_s * factor**(k-1), max_delay_s)`` seconds (wall clock)."""
    attempts: int = 5
    first_delay_s: float = 0.05
    factor: float = 2.0
    max_delay_s: float = 2.0

    def __post_init__(self):
        if self.attempts < 1:
            raise ValueError(f"retry attempts must be >= 1, got {self.attempts}")
        if self.first_delay_s < 0 or self.max_delay_s < 0 or self.factor < 1:
            raise ValueError(f"retry delays must be >= 0 and factor >= 1, got {self}")

    def delay_s(self, failed_attempt: int) -> float:
        """Wait after the ``failed_attempt``-th failure (1-based)."""
        return min(self.first_delay_s * self.factor ** (failed_attempt - 1), self.max_delay_s)


def retry(action: Callable[[], T], *, instrument: str, what: str, policy: RetryPolicy,
          timeout_s: float | None = None,
          recover: Callable[[InstrumentError], None] | None = None) -> T:
    """Run ``action`` until it succeeds, at most ``policy.attempts`` times and (when given) not
    past ``timeout_s`` seconds from now. Between attempts: wait the back-off, then call
    ``recover(error)`` (resynchronise the line, reopen the port, redo a set-up); an error raised
    by ``recover`` counts as that attempt's failure."""
    start = time.monotonic()
    deadline = None if timeout_s is None else start + timeout_s
    errors: list[InstrumentError] = []
    attempt = 0
    while True:
        attempt += 1
        try:
            if attempt > 1 and recover is not None:
                recover(errors[-1])
            return action()
        except InstrumentRejected:
            raise
        except InstrumentError as exc:
            errors.append(exc)
            delay = policy.delay_s(attempt)
            elapsed = time.monotonic() - start
            out_of_time = deadline is not None and time.monotonic() + delay >= deadline
            if attempt >= policy.attempts or out_of_time:
                cls = (InstrumentTimeout if all(isinstance(e, InstrumentTimeout) for e in errors)
                       else InstrumentError)
                log.error("%s: %s failed %d time(s) in %.2f s; giving up: %s",
                          instrument, what, attempt, elapsed, exc.reason)
                raise cls(instrument, f"{what} failed {attempt} time(s) in {elapsed:.2f} s "
                                      f"(retry limit {policy.attempts} attempts"
                                      f"{'' if timeout_s is None else f', {timeout_s:g} s'}); "
                                      f"last error: {exc.reason}", exc.code) from exc
            log.warning("%s: %s attempt %d/%d failed (%s: %s); retrying in %.3f s",
                        instrument, what, attempt, policy.attempts, type(exc).__name__,
                        exc.reason, delay)
            time.sleep(delay)
