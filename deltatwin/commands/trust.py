"""``--trust-effects``: the user's consent to run the code of the user effects a file names.

A scenario or a fitted model may name a user effect (``path/to/effects.py:Class``); reading
the file imports that Python file, which may do anything, as unpickling a file may. The commands
that read such files refuse it (one line naming the file and the code, exit 2) unless the user
passes ``--trust-effects`` (every user effect the files name) or ``--trust-effects SPEC`` (only
the code of that spec: a ``file.py[:Class]`` or ``module[:Class]``; repeatable), as Hugging
Face's ``trust_remote_code`` does. The Python readers take ``trust_effects=`` the same way.
"""
from __future__ import annotations

EVERY = "*"


def add_trust_option(parser) -> None:
    parser.add_argument(
        "--trust-effects", action="append", nargs="?", const=EVERY, default=[],
        metavar="FILE.py[:Class]",
        help="run the code of the user effects (file.py:Class) the scenario or model files name; "
             "without it such a file is refused, as its code may do anything. With a value, "
             "only that file's (or module's) code (repeatable)")


def trust_of(args) -> bool | list[str]:
    """What ``--trust-effects`` consents to: True (every user effect), the specs given, or
    False (none)."""
    given = getattr(args, "trust_effects", [])
    return True if EVERY in given else list(given) or False
