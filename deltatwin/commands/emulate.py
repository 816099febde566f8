"""``deltatwin emulate SCENARIO``: the scenario's twin served as serial instruments.

One emulator per instrument (robot controller, SP-2000, two LDS1000, Keithley 2700, coil supply,
and the clock port that carries the twin's simulated time), each on its own pseudo-terminal
(published as a symlink in ``--dir``) or, with ``--tcp``, on a ``socket://`` port; all backed by
one twin built from the scenario exactly as ``deltatwin simulate`` builds it (same seed, same
scale -> the same data). Prints the device paths, writes the ports file (``--ports-out``) that
``campaign --instruments serial --ports`` reads, and serves until interrupted (Ctrl-C, SIGTERM).
"""
from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path

from deltatwin.commands.output import strict_json
from deltatwin.commands.trust import add_trust_option, trust_of


def register(sub) -> None:
    p = sub.add_parser("emulate", help="serve a scenario's twin as serial instruments (one "
                                       "pseudo-terminal each) until interrupted",
                       description=__doc__.split("\n\n")[1])
    p.add_argument("scenario", help="scenario TOML path or name in scenarios/")
    p.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--reduced", action="store_true", help="the scenario's reduced scale")
    g.add_argument("--scale", type=float, default=None, help="fraction of the campaign's points, "
                   "0 < SCALE <= 1 (use the same as the campaign: the twin's time horizon depends on it)")
    p.add_argument("--ports-out", type=Path, default=None, help="write the ports file (TOML)")
    p.add_argument("--dir", type=Path, default=None,
                   help="folder for the device symlinks (default: a temporary folder)")
    p.add_argument("--tcp", action="store_true", help="serve socket://127.0.0.1:PORT "
                                                      "instead of pseudo-terminals")
    p.add_argument("--realtime", action="store_true",
                   help="pace the twin's clock by the wall clock (default: as fast as the "
                        "serial exchanges allow)")
    p.add_argument("--timeout-s", type=float, default=None,
                   help="per-reply timeout written to the ports file (default: per instrument)")
    p.add_argument("--json", action="store_true", help="print the devices as one JSON line")
    add_trust_option(p)
    p.set_defaults(func=run)


# the twin's parasitic rotations stay within +-95 arcsec over the workspace (paper-thermal,
# paper-force; steps between points <= 19 arcsec): a step above 200 arcsec is a damaged reply
TWIN_AC_MAX_STEP_ARCSEC = 200.0

def simulated_instruments(scenario: str, seed: int | None, reduced: bool, scale: float | None,
                          trust_effects=False):
    """The twin's simulated ``InstrumentSet`` for a scenario, built as ``simulate`` builds it
    (``trust_effects``: ``Scenario.load``'s)."""
    from deltatwin.twin.instruments.simulated import SimulatedLab
    from deltatwin.twin.scenario import Scenario, check_scale

    check_scale(scale, "--scale")
    sc = Scenario.load(scenario, seed=seed, trust_effects=trust_effects)
    scale = sc.reduced_scale if reduced else scale
    twin, _ = sc.build(scale)
    return sc, scale, SimulatedLab(twin, sc.settings).instrument_set()


def serve(instruments, *, name: str, directory: Path | None, ports_out: Path | None,
          tcp: bool, realtime: bool, timeout_s: float | None, as_json: bool,
          stop: threading.Event, world: dict | None = None) -> int:
    """Run the emulated laboratory until ``stop`` is set; prints the devices, then ``ready``."""
    from deltatwin.hw.emulators.lab import EmulatedLab
    from deltatwin.hw.ports import write_ports

    with EmulatedLab(instruments, directory, link="tcp" if tcp else "pty", realtime=realtime,
                     timeout_s=timeout_s, name=name, world=world,
                     ac_max_step_arcsec=TWIN_AC_MAX_STEP_ARCSEC) as lab:
        devices = lab.devices()
        if ports_out is not None:
            write_ports(ports_out, lab.ports(),
                        comment=f"emulated laboratory for {name}: valid while `deltatwin "
                                f"emulate` runs")
        if as_json:
            print(strict_json({"devices": {n: {"url": u, "device": d}
                                          for n, (u, d) in devices.items()},
                              "ports": None if ports_out is None else str(ports_out)}))
        else:
            for n, (url, device) in devices.items():
                print(f"  {n:>16}: {url}" + (f" -> {device}" if device != url else ""))
            if ports_out is not None:
                print(f"  ports file: {ports_out}")
            print("ready (Ctrl-C to stop)")
        sys.stdout.flush()
        while not stop.wait(0.5):      # wakes for the signal handlers twice a second
            pass
    return 0


def run(args) -> int:
    if args.timeout_s is not None and not args.timeout_s > 0:
        raise ValueError(f"--timeout-s must be > 0, got {args.timeout_s}")
    sc, scale, instruments = simulated_instruments(args.scenario, args.seed, args.reduced,
                                                   args.scale, trust_of(args))
    stop = threading.Event()
    # SIGINT is handled explicitly too: a process started in the background by a shell (`&`)
    # inherits SIGINT ignored, and Ctrl-C / kill -INT would then never stop the emulator
    previous = {sig: signal.signal(sig, lambda *_: stop.set())
                for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        return serve(instruments, name=f"{sc.name} (seed {sc.seed})", directory=args.dir,
                     ports_out=args.ports_out, tcp=args.tcp, realtime=args.realtime,
                     timeout_s=args.timeout_s, as_json=args.json, stop=stop,
                     world=sc.identity(scale))
    except KeyboardInterrupt:
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
