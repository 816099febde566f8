"""Keithley 2700 + multiplexer emulator: SCPI parsed as IEEE 488.2 / SCPI-99 say (hw/scpi.py:
long and short forms, any case, optional leading colon, ``;`` chaining, whitespace, CR LF),
the set-up state per channel, the error queue (10 entries, like the instrument), 4-wire PT100
scans answered from the backing ``ThermometerScanner``.

Declared commands (``COMMANDS``): the common commands ``*IDN? *RST *CLS *OPC? *OPC *STB? *ESR?
*OPT? *WAI``; ``SYSTem:ERRor[:NEXT]?``, ``SYSTem:PRESet``, ``SYSTem:RNUMber:RESet``, ``STATus:QUEue:CLEar``,
``STATus:PRESet``; ``ROUTe:OPEN:ALL``, ``ROUTe:MULTiple:CLOSe[?]``, ``ROUTe:MULTiple:OPEN``,
``ROUTe:SCAN[:INTernal][?]``, ``ROUTe:SCAN:LSELect``, ``ROUTe:SCAN:TSOurce``;
``[SENSe:]FUNCtion 'TEMPerature'[, (@list)]``, ``[SENSe:]TEMPerature:TRANsducer``,
``[SENSe:]TEMPerature:FRTD:TYPE``; ``INITiate:CONTinuous[?]``, ``TRIGger:SOURce``,
``TRIGger:COUNt``, ``SAMPle:COUNt``; ``FORMat:ELEMents[?]``; ``READ?``, ``FETCh?``.

A channel with no sensor behind it, or one listed in ``open_channels`` (an open PT100 lead),
reads ``+9.9E37`` (overflow). Errors go to the queue (``SYST:ERR?``): ``-113,"Undefined header"``
and the other parser errors of hw/scpi.py; a channel that is not on the cards
``-222,"Parameter data out of range"``; ``READ?`` before the 4-wire PT100 scan is set up
``-221,"Settings conflict"`` and no reply; a line longer than 255 characters
``-363,"Input buffer overrun"``; a backing failure or an injected ``error_code`` (default -230,
"Data corrupt or stale") -> queued, and a query gets no reply.

Power-on, ``*RST`` and ``SYSTem:PRESet`` as the Model 2700 User's Manual says (section 8,
"Idle"; the Model 2701 manual's "Remote programming - scanning" likewise): the instrument powers
on to the factory default setup, which ``SYSTem:PRESet`` restores, with continuous initiation
ON; ``*RST`` restores the *RST defaults, the one-shot mode: continuous initiation OFF. Both lose
the set-up (channels, scan list); neither clears the error queue or the reading counter.

The reading number counts every reading since power-on (``SYSTem:RNUMber:RESet`` restarts it at
0); it is written with at least 5 digits and grows past 99,999 (``+100043RDNG#``), as the
manual's figure shows it without a fixed width (``+236RDNG``). The relative timestamp restarts
at 0 after 99,999.99 s, as the manual says.
"""
from __future__ import annotations

from collections import deque

from deltatwin.hw.emulators.base import LineEmulator
from deltatwin.hw.keithley2700 import PROTOCOL, format_element
from deltatwin.hw.scpi import ScpiCommand as C
from deltatwin.hw.scpi import ScpiError, ScpiParser, channel_list, choice, choices, integer, quoted
from deltatwin.twin.instruments.interface import InstrumentError

QUEUE_SIZE = 10
TIMESTAMP_WRAP_S = 100000.0     # the relative timestamp restarts after 99,999.99 s
ELEMENTS = ("READing", "UNITs", "TSTamp", "RNUMber", "CHANnel")
DEFAULT_ELEMENTS = ("READING", "UNITS", "TSTAMP", "RNUMBER", "CHANNEL")
ON_OFF = ("ON", "OFF", "1", "0")

COMMANDS = ScpiParser([
    C("*IDN", "identify", query=True),
    C("*RST", "reset"),
    C("*CLS", "clear"),
    C("*OPC", "operation_complete_query", query=True),
    C("*OPC", "operation_complete"),
    C("*STB", "status_byte", query=True),
    C("*ESR", "event_status", query=True),
    C("*OPT", "options", query=True),
    C("*WAI", "wait"),
    C("SYSTem:ERRor[:NEXT]", "error", query=True),
    C("SYSTem:PRESet", "preset"),
    C("SYSTem:RNUMber:RESet", "reading_number_reset"),
    C("STATus:QUEue:CLEar", "clear_queue"),
    C("STATus:PRESet", "status_preset"),
    C("ROUTe:OPEN:ALL", "open_all"),
    C("ROUTe:MULTiple:CLOSe", "closed_channels", query=True),
    C("ROUTe:MULTiple:CLOSe", "close_channels", (channel_list(),)),
    C("ROUTe:MULTiple:OPEN", "open_channel_list", (channel_list(),)),
    C("ROUTe:SCAN[:INTernal]", "scan_list", (channel_list(),)),
    C("ROUTe:SCAN[:INTernal]", "scan_list_query", query=True),
    C("ROUTe:SCAN:LSELect", "scan_list_select", (choice("INTernal", "NONE"),)),
    C("ROUTe:SCAN:TSOurce", "scan_trigger", (choice("IMMediate", "SPECific"),)),
    C("[SENSe:]FUNCtion", "function",
      (quoted("TEMPerature", "VOLTage", "RESistance", "FRESistance"), channel_list(True))),
    C("[SENSe:]TEMPerature:TRANsducer", "transducer",
      (choice("FRTD", "RTD", "TCouple", "THERmistor"), channel_list(True))),
    C("[SENSe:]TEMPerature:FRTD:TYPE", "rtd_type",
      (choice("PT100", "D100", "F100", "PT3916", "PT385", "USER"), channel_list(True))),
    C("INITiate:CONTinuous", "continuous", (choice(*ON_OFF),)),
    C("INITiate:CONTinuous", "continuous_query", query=True),
    C("TRIGger:SOURce", "trigger_source",
      (choice("IMMediate", "TIMer", "MANual", "BUS", "EXTernal"),)),
    C("TRIGger:COUNt", "trigger_count", (integer(1, 55000),)),
    C("SAMPle:COUNt", "sample_count", (integer(1, 55000),)),
    C("FORMat:ELEMents", "format_elements", (choices(*ELEMENTS),)),
    C("FORMat:ELEMents", "format_elements_query", query=True),
    C("READ", "read", query=True),
    C("FETCh", "fetch", query=True),
])


class Keithley2700Emulator(LineEmulator):
    protocol = PROTOCOL
    default_error_code = -230

    def __init__(self, backing, link, channels: dict[int, str], card_channels: int = 40, **kw):
        super().__init__(backing, link, **kw)
        self.channels = dict(channels)       # channel -> backing sensor name
        self.card_channels = card_channels   # channels per multiplexer card (slots 1 and 2)
        self.open_channels: set[int] = set()
        self.errors: deque[tuple[int, str]] = deque(maxlen=QUEUE_SIZE)
        self.readings_taken = 0              # the reading counter (RNUM)
        self._t0 = backing.instruments.clock.now()
        self.reset(continuous=True)          # power-on: the factory default setup

    def reset(self, continuous: bool = False) -> None:
        """The set-up is lost (the error queue and reading counter are not); continuous
        initiation OFF as ``*RST`` leaves it, ON as power-on and ``SYSTem:PRESet`` do."""
        self.function: dict[int, str] = {}       # per channel, as set by SENS:FUNC
        self.transducer: dict[int, str] = {}
        self.rtd_type: dict[int, str] = {}
        self.scan: tuple[int, ...] = ()
        self.scan_select = "NONE"
        self.continuous = continuous
        self.trigger_source = "IMMEDIATE"
        self.scan_trigger = "SPECIFIC"
        self.elements = DEFAULT_ELEMENTS
        self.closed: tuple[int, ...] = ()
        self.last_reply: str | None = None

    def _queue(self, code: int, reason: str) -> None:
        self.errors.append((code, reason))

    # ---- the line: every unit in turn, the queries' replies joined with ';'
    def parse_request(self, line: str):
        return ("scpi", {"line": line}), COMMANDS.has_query(line)

    def handle(self, command: str, values: dict) -> str | None:
        replies: list[str] = []

        def run(unit) -> None:
            reply = getattr(self, f"on_{unit.command.name}")(*unit.values)
            if unit.command.query and reply is not None:
                replies.append(reply)
        try:
            COMMANDS.parse(values["line"], run)
        except ScpiError as exc:
            self._queue(exc.code, exc.message)
        return ";".join(replies) if replies else None

    def unknown(self, line: str) -> str | None:      # every line parses as "scpi"
        raise AssertionError("unreachable")

    def overlong(self) -> str | None:
        self._queue(-363, "Input buffer overrun")
        return None

    def fail(self, error: InstrumentError, request) -> str | None:
        code = error.code if isinstance(error.code, int) else -240
        self._queue(code, error.reason if isinstance(error.code, int) else
                    f"Hardware error: {error.reason}")
        return None

    # ---- checks
    def _on_cards(self, channels) -> tuple[int, ...]:
        if any(not (c // 100 in (1, 2) and 1 <= c % 100 <= self.card_channels)
               for c in channels or ()):
            raise ScpiError(-222, "Parameter data out of range")
        return tuple(channels or ())

    # ---- common commands
    def on_identify(self):
        return "KEITHLEY INSTRUMENTS INC.,MODEL 2700,4022795,B09  /A02"

    def on_reset(self):
        self.reset()

    def on_clear(self):
        self.errors.clear()

    def on_operation_complete_query(self):
        return "1"            # every command completes before the next is parsed

    def on_operation_complete(self):
        pass

    def on_status_byte(self):
        return str(4 if self.errors else 0)     # bit 2: error queue not empty

    def on_event_status(self):
        return "0"

    def on_options(self):
        return ",".join(["7702", "7702"] if self.card_channels == 40 else ["7700", "7700"])

    def on_wait(self):
        pass

    # ---- system, status, routes
    def on_error(self):
        code, reason = self.errors.popleft() if self.errors else (0, "No error")
        return f'{code},"{reason}"'

    def on_preset(self):
        self.reset(continuous=True)

    def on_reading_number_reset(self):
        self.readings_taken = 0

    def on_clear_queue(self):
        self.errors.clear()

    def on_status_preset(self):
        pass

    def on_open_all(self):
        self.closed = ()

    def on_closed_channels(self):
        return "(@" + ",".join(str(c) for c in self.closed) + ")"

    def on_close_channels(self, channels):
        self.closed = self._on_cards(channels)

    def on_open_channel_list(self, channels):
        opened = self._on_cards(channels)
        self.closed = tuple(c for c in self.closed if c not in opened)

    def on_scan_list(self, channels):
        self.scan = self._on_cards(channels)

    def on_scan_list_query(self):
        return "(@" + ",".join(str(c) for c in self.scan) + ")"

    def on_scan_list_select(self, mode):
        self.scan_select = mode

    def on_scan_trigger(self, source):
        self.scan_trigger = source

    # ---- measurement set-up (per channel)
    def on_function(self, name, channels):
        for c in self._on_cards(channels):
            self.function[c] = name

    def on_transducer(self, kind, channels):
        for c in self._on_cards(channels):
            self.transducer[c] = kind

    def on_rtd_type(self, kind, channels):
        for c in self._on_cards(channels):
            self.rtd_type[c] = kind

    def on_continuous(self, state):
        self.continuous = state in ("ON", "1")

    def on_continuous_query(self):
        return "1" if self.continuous else "0"

    def on_trigger_source(self, source):
        self.trigger_source = source

    def on_trigger_count(self, n):
        pass

    def on_sample_count(self, n):
        pass

    def on_format_elements(self, elements):
        self.elements = tuple(e for e in DEFAULT_ELEMENTS if e in elements)

    def on_format_elements_query(self):
        return ",".join(e[:4] for e in self.elements)

    # ---- readings
    def _pt100_scan_ready(self) -> bool:
        return bool(self.scan) and self.scan_select == "INTERNAL" and not self.continuous \
            and self.trigger_source == "IMMEDIATE" and self.scan_trigger == "IMMEDIATE" \
            and all(self.function.get(c) == "TEMPERATURE" and self.transducer.get(c) == "FRTD"
                    and self.rtd_type.get(c) == "PT100" for c in self.scan)

    def on_read(self):
        if not self._pt100_scan_ready():
            raise ScpiError(-221, "Settings conflict")
        scan = self.backing.call(self.backing.instruments.thermometers.scan)
        secs = (scan.t_s - self._t0) % TIMESTAMP_WRAP_S
        elements = []
        for chan in self.scan:
            sensor = self.channels.get(chan)
            value = (float("inf") if sensor is None or chan in self.open_channels
                     else scan.temperatures_C[sensor])
            self.readings_taken += 1
            elements.append(format_element(self.elements, value, secs, self.readings_taken,
                                           chan))
        self.last_reply = ",".join(elements)
        return self.last_reply

    def on_fetch(self):
        if self.last_reply is None:
            raise ScpiError(-230, "Data corrupt or stale")
        return self.last_reply
