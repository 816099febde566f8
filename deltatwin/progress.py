"""How a long run shows progress on stderr, in one place: on a terminal one updating line (a
tqdm bar, or a status line rewritten in place); anywhere else (a log file, a pipe, CI) plain
lines, at most one every ``PLAIN_INTERVAL_S`` seconds per task and never the same text twice,
so a redirected log holds no carriage-return runs and no repeated line.

``progress_bar(...)`` takes tqdm's arguments. Library code that reports a changing status logs
it with ``extra={"progress": TASK}``; the command line's ``ProgressHandler`` shows such records
as described (other records as plain lines). ``TQDM_DISABLE`` (tqdm's own switch, set to
anything but "" or "0") silences both the bars and these status lines: for output that must
not depend on the machine's speed (docs/walkthrough.md is generated so). The ground floor:
every layer may import this module; it imports nothing of the project."""
from __future__ import annotations

import logging
import os
import sys
import time

PLAIN_INTERVAL_S = 5.0     # off a terminal: at most one progress line per task this often


def silenced() -> bool:
    """Whether progress is switched off (``TQDM_DISABLE``, as tqdm reads it)."""
    return os.environ.get("TQDM_DISABLE", "") not in ("", "0")


def is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):          # closed, or no isatty (a StringIO)
        return False


class _PlainLines:
    """A file for tqdm off a terminal: each carriage-return update becomes a line of its own,
    a repeated text is dropped (tqdm's ``mininterval`` spaces them)."""

    def __init__(self, stream):
        self.stream = stream
        self.last = None

    def write(self, text: str) -> None:
        for part in text.replace("\r", "\n").split("\n"):
            part = part.rstrip()
            if part and part != self.last:
                self.stream.write(part + "\n")
                self.last = part

    def flush(self) -> None:
        self.stream.flush()


def progress_bar(*args, file=None, **kwargs):
    """A tqdm bar on stderr (or ``file``): updating in place on a terminal; off one, plain
    lines at most every ``PLAIN_INTERVAL_S`` s (and the last state when it closes)."""
    from tqdm import tqdm

    stream = file or sys.stderr
    if is_terminal(stream):
        return tqdm(*args, file=stream, **kwargs)
    kwargs.setdefault("mininterval", PLAIN_INTERVAL_S)
    kwargs.setdefault("maxinterval", 10 * PLAIN_INTERVAL_S)
    return tqdm(*args, file=_PlainLines(stream), ascii=True, ncols=80, **kwargs)


class ProgressHandler(logging.StreamHandler):
    """Log records on a stream, those with a ``progress`` attribute (a task name) as
    progress: on a terminal one line rewritten in place, ended by the next other record;
    off one, a plain line when its text changed and ``PLAIN_INTERVAL_S`` s have passed since
    the task's last line (its first line always)."""

    def __init__(self, stream=None, clock=time.monotonic):
        super().__init__(stream if stream is not None else sys.stderr)
        self.clock = clock
        self.shown: dict[str, tuple[float, str]] = {}     # task -> (time, text) last shown
        self.open_line = False                            # a status line awaits its end

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
            task = getattr(record, "progress", None)
            if task is not None and silenced():
                return
            terminal = is_terminal(self.stream)
            if task is None:
                self._end_line()
                self.stream.write(text + "\n")
            elif terminal:
                self.stream.write("\r" + text + "\x1b[K")
                self.open_line = True
            else:
                last_t, last_text = self.shown.get(task, (-float("inf"), None))
                now = self.clock()
                if text == last_text or now - last_t < PLAIN_INTERVAL_S:
                    return
                self.shown[task] = (now, text)
                self.stream.write(text + "\n")
            self.flush()
        except Exception:                                 # noqa: BLE001 - logging's contract
            self.handleError(record)

    def _end_line(self) -> None:
        if self.open_line:
            self.stream.write("\n")
            self.open_line = False

    def close(self) -> None:
        try:
            self._end_line()
        finally:
            super().close()
