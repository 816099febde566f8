"""SCPI request parsing for the emulators, as IEEE 488.2 / SCPI-99 prescribe.

An emulated SCPI instrument DECLARES its commands (``ScpiCommand``: a header in the standard's
notation, e.g. ``"[SENSe:]TEMPerature:TRANsducer"`` with optional nodes in brackets and the
short form in upper case, whether it is a query, and typed parameters), like PyMeasure's
properties; ``ScpiParser`` turns a received line into the declared commands it holds:

* headers are case-insensitive, in long or short form (``SENSe:FUNCtion`` = ``SENS:FUNC`` =
  ``sens:func``), with an optional leading colon;
* several program message units on one line, separated by ``;``; a unit without a leading colon
  is relative to the path of the previous one (IEEE 488.2 section 7.6.1), common commands
  (``*IDN?``) leave that path alone;
* whitespace between header and parameters, around commas and at the ends; a CR before the LF
  terminator is stripped;
* errors are SCPI error codes (``ScpiError``): ``-102`` syntax error, ``-108`` parameter not
  allowed, ``-109`` missing parameter, ``-113`` undefined header, ``-224`` illegal parameter
  value; parsing stops at the first error (the rest of the line is discarded, as instruments
  do after a command error).

Parameters are ``Param`` objects: ``choice`` (a character-data mnemonic, long or short form ->
its long form in upper case), ``quoted`` (a string in ' or " whose content is a ``choice``),
``integer``, ``channel_list`` (``(@101:103,105)`` -> a tuple of channels) and ``choices``
(a comma-separated list of mnemonics, e.g. ``FORM:ELEM READ,UNIT``).
"""
from __future__ import annotations

import itertools
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

_MNEMONIC = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
_PATH = re.compile(r":?[A-Za-z][A-Za-z0-9_]*(?::[A-Za-z][A-Za-z0-9_]*)*\??")
_COMMON = re.compile(r"\*[A-Za-z]+\??")


class ScpiError(Exception):
    """A SCPI error: ``code`` (negative, standard) and its standard ``message``."""

    def __init__(self, code: int, message: str):
        super().__init__(f"{code},{message}")
        self.code, self.message = code, message


def _forms(spec: str) -> tuple[str, str]:
    """``"SENSe"`` -> (``"SENS"``, ``"SENSE"``): the short form is the upper-case part."""
    return "".join(c for c in spec if c.isupper() or c.isdigit() or c == "*"), spec.upper()


# --------------------------------------------------------------------------- parameters

@dataclass(frozen=True)
class Param:
    """One parameter: ``parse`` text (stripped) -> value, raising ``ScpiError(-224)`` when the
    value is not allowed; ``optional`` parameters may be left out at the end."""
    parse: Callable[[str], Any]
    optional: bool = False


def _illegal() -> ScpiError:
    return ScpiError(-224, "Illegal parameter value")


def choice(*specs: str, optional: bool = False) -> Param:
    forms = {f: _forms(s)[1] for s in specs for f in _forms(s)}

    def parse(text: str) -> str:
        try:
            return forms[text.upper()]
        except KeyError:
            raise _illegal() from None
    return Param(parse, optional)


def choices(*specs: str) -> Param:
    one = choice(*specs).parse
    return Param(lambda text: tuple(one(t.strip()) for t in _split(text, ",")))


def quoted(*specs: str, optional: bool = False) -> Param:
    one = choice(*specs).parse

    def parse(text: str) -> str:
        if len(text) < 2 or text[0] not in "'\"" or text[-1] != text[0]:
            raise _illegal()
        return one(text[1:-1].strip())
    return Param(parse, optional)


def integer(lo: int, hi: int, optional: bool = False) -> Param:
    def parse(text: str) -> int:
        try:
            value = float(text)           # SCPI numeric: 1, +1, 1.0, 1E0
        except ValueError:
            raise ScpiError(-104, "Data type error") from None
        if not (lo <= value <= hi) or value != int(value):
            raise ScpiError(-222, "Parameter data out of range")
        return int(value)
    return Param(parse, optional)


def channel_list(optional: bool = False) -> Param:
    """``(@101:103,105)`` -> (101, 102, 103, 105); ``(@)`` -> ()."""
    def parse(text: str) -> tuple[int, ...]:
        body = re.fullmatch(r"\(\s*@(.*)\)", text, re.S)
        if body is None:
            raise ScpiError(-104, "Data type error")
        out: list[int] = []
        for part in filter(None, (p.strip() for p in body[1].split(","))):
            m = re.fullmatch(r"(\d{3})(?:\s*:\s*(\d{3}))?", part)
            if m is None:
                raise ScpiError(-224, "Illegal parameter value")
            lo, hi = int(m[1]), int(m[2] or m[1])
            if hi < lo:
                raise ScpiError(-224, "Illegal parameter value")
            out.extend(range(lo, hi + 1))
        return tuple(out)
    return Param(parse, optional)


# --------------------------------------------------------------------------- commands

@dataclass(frozen=True)
class ScpiCommand:
    """``header`` in SCPI notation (``"ROUTe:SCAN[:INTernal]"``, ``"*IDN"``), ``query`` (the
    header ends in ``?``), ``name`` (the emulator's handler is ``on_<name>``) and ``params``."""
    header: str
    name: str
    params: tuple[Param, ...] = ()
    query: bool = False
    paths: tuple[tuple[str, ...], ...] = field(init=False, repr=False)

    def __post_init__(self):
        # every spelling of the header: optional nodes in or out, each node long or short
        nodes = re.findall(r"(\[?):?([A-Za-z*][A-Za-z0-9]*)\]?", self.header)
        per_node = [[_forms(n)[0], _forms(n)[1]] + ([None] if opt else []) for opt, n in nodes]
        paths = {tuple(x for x in combo if x is not None) for combo in itertools.product(*per_node)}
        object.__setattr__(self, "paths", tuple(paths))


def _split(text: str, sep: str) -> list[str]:
    """``text`` split at ``sep`` outside quotes and parentheses."""
    parts, depth, quote, start = [], 0, "", 0
    for i, c in enumerate(text):
        if quote:
            quote = "" if c == quote else quote
        elif c in "'\"":
            quote = c
        elif c == "(":
            depth += 1
        elif c == ")":
            depth -= 1
        elif c == sep and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return parts


@dataclass(frozen=True)
class Unit:
    """One parsed program message unit: the declared command and its parameter values."""
    command: ScpiCommand
    values: tuple


class ScpiParser:
    """The declared commands of one instrument."""

    def __init__(self, commands: list[ScpiCommand]):
        self.commands = list(commands)
        self._by_path: dict[tuple[tuple[str, ...], bool], ScpiCommand] = {}
        for cmd in self.commands:
            for path in cmd.paths:
                key = (path, cmd.query)
                if key in self._by_path:
                    raise ValueError(f"SCPI header {cmd.header!r} collides with "
                                     f"{self._by_path[key].header!r}")
                self._by_path[key] = cmd

    def has_query(self, line: str) -> bool:
        """Whether ``line`` holds a query (so the instrument would answer it)."""
        return any(unit.split(None, 1)[0].endswith("?")
                   for unit in (u.strip() for u in _split(line.strip(), ";")) if unit)

    def parse(self, line: str, on_unit: Callable[[Unit], None]) -> None:
        """Parse ``line`` unit by unit, calling ``on_unit`` for each one as it is parsed (so a
        unit runs before a later one fails to parse, as on an instrument). Raises ``ScpiError``
        at the first unit that cannot be parsed."""
        prefix: tuple[str, ...] = ()
        for raw in _split(line.strip(), ";"):
            unit = raw.strip()
            if not unit:
                continue
            header, arg = re.fullmatch(r"(\S+)\s*(.*)", unit, re.S).groups()
            query = header.endswith("?")
            if _COMMON.fullmatch(header.lstrip(":")):
                path = (header.lstrip(":").rstrip("?").upper(),)
            elif _PATH.fullmatch(header):
                nodes = tuple(header.rstrip("?").lstrip(":").upper().split(":"))
                path = nodes if header.startswith(":") else prefix + nodes
                prefix = path[:-1]
            else:
                raise ScpiError(-102, "Syntax error")
            cmd = self._by_path.get((path, query))
            if cmd is None:
                raise ScpiError(-113, "Undefined header")
            on_unit(Unit(cmd, self._params(cmd, arg)))

    @staticmethod
    def _params(cmd: ScpiCommand, arg: str) -> tuple:
        if not cmd.params:
            if arg:
                raise ScpiError(-108, "Parameter not allowed")
            return ()
        # a list-valued last parameter (``choices``) takes the rest of the line
        texts = [t.strip() for t in _split(arg, ",")] if arg else []
        if len(cmd.params) == 1 and texts:
            texts = [arg]
        elif len(texts) > len(cmd.params):
            raise ScpiError(-108, "Parameter not allowed")
        if any(t == "" for t in texts):
            raise ScpiError(-102, "Syntax error")
        missing = cmd.params[len(texts):]
        if any(not p.optional for p in missing):
            raise ScpiError(-109, "Missing parameter")
        return tuple(p.parse(t) for p, t in zip(cmd.params, texts)) + (None,) * len(missing)
