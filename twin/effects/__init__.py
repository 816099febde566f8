"""The library of physical effects: each a plug-in with a name, documented parameters (units,
defaults) and the stages of the twin it changes (see base.py). A scenario switches them on by
name; ``deltatwin effects`` lists them.

The researcher's own effects join the library the same way (docs/effects.md), named by a spec:

* ``path/to/my_effects.py:ClassName``: an ``Effect`` subclass in a Python file (a relative path
  is taken from ``base_dir``: the working directory, or the scenario file's folder);
* ``package.module:ClassName``: the same from an importable module;
* a name exposed by an installed package's entry point in the ``deltatwin.effects`` group.

Once resolved, a user effect is also known by its ``name``. Errors in its file (at import) or in
its hooks (at evaluation) are reported as an ``EffectError`` naming the file and line.

A user effect is code: a file (a scenario, a fitted model) that names one would run it when
read. The readers of files therefore pass ``trust``: False (the default of ``Scenario.load``,
``load_fitted``, ...) refuses every ``file.py:Class`` and ``module:Class`` a file names with an
``UntrustedEffectError`` naming the file and the code; True runs them; a collection of specs runs
only the code those name (the same file or module the user gave on the command line). A spec
given directly (``effect_class``, ``PhysicsFit([...])``, ``fit --effects``) is the user's own
choice and trusted. Library effects and installed entry points need no consent.
"""
from __future__ import annotations

import ast
import difflib
import functools
import hashlib
import importlib
import importlib.util
import inspect
import keyword
import sys
import traceback
from importlib.metadata import entry_points
from pathlib import Path

from deltatwin.twin.effects.air_refraction import AirRefraction
from deltatwin.twin.effects.base import Effect, EffectError, Parameter, shift_reading
from deltatwin.twin.effects.beam_misalignment import BeamMisalignment
from deltatwin.twin.effects.coil_heating import CoilHeating
from deltatwin.twin.effects.geometric_errors import GeometricErrors
from deltatwin.twin.effects.gravity_sag import GravitySag
from deltatwin.twin.effects.loop_drift import LoopDrift
from deltatwin.twin.effects.magnetic_force import MagneticForce
from deltatwin.twin.effects.motor_heating import MotorHeating
from deltatwin.twin.effects.peltier_supports import PeltierSupports
from deltatwin.twin.effects.room_climate import RoomClimate
from deltatwin.twin.effects.sensor_contact import SensorContact
from deltatwin.twin.effects.servo_settling import ServoSettling
from deltatwin.twin.effects.thermal_expansion import ThermalExpansion

LIBRARY: dict[str, type[Effect]] = {cls.name: cls for cls in (
    GeometricErrors, ThermalExpansion, GravitySag, MagneticForce, LoopDrift, AirRefraction,
    BeamMisalignment, SensorContact, ServoSettling, RoomClimate, PeltierSupports, MotorHeating, CoilHeating)}

ENTRY_POINT_GROUP = "deltatwin.effects"
# every hook a user effect may define (base.py's stage hooks), each guarded by ``_guarded``
HOOKS = ("robot", "environment", "heat_sources", "motor_settling", "thermometers",
         "sensed_parts", "part_temperatures", "motor_angles", "wrench", "wrench_derivatives",
         "optics")

# user effects resolved so far: by their name, and the spec each was loaded from
_USER: dict[str, type[Effect]] = {}
_SOURCE: dict[type, str] = {}


def _where_in(path: str, exc: BaseException) -> str:
    """'file:line' of the deepest frame of ``exc``'s traceback inside ``path``."""
    if isinstance(exc, SyntaxError) and exc.filename == path:
        return f"{path}:{exc.lineno}"
    frames = [f for f in traceback.extract_tb(exc.__traceback__) if f.filename == path]
    return f"{path}:{frames[-1].lineno}" if frames else path


def _guarded(cls: type[Effect], path: str) -> type[Effect]:
    """``cls`` with every hook it defines reporting an exception as an EffectError naming the
    user's file and line (the hooks' results are unchanged)."""
    def wrap(hook, fn):
        @functools.wraps(fn)
        def call(self, *args, **kwargs):
            try:
                return fn(self, *args, **kwargs)
            except EffectError:
                raise
            except Exception as exc:
                raise EffectError(f"{_where_in(path, exc)}: effect {cls.name!r}, stage "
                                  f"{hook!r}: {type(exc).__name__}: {exc}") from exc
        return call
    for hook in HOOKS:
        if hook in vars(cls):
            setattr(cls, hook, wrap(hook, vars(cls)[hook]))
    return cls


def _checked(obj, spec: str, where: str) -> type[Effect]:
    """``obj`` if it is a well-formed Effect subclass (name, summary, parameters), else an
    EffectError naming ``spec``."""
    if not (isinstance(obj, type) and issubclass(obj, Effect)) or obj is Effect:
        raise EffectError(f"{where}: {spec!r} is not a subclass of deltatwin.twin.effects.Effect "
                          f"(got {obj!r})")
    name = getattr(obj, "name", None)
    if not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name):
        raise EffectError(f"{where}: {spec!r}: class attribute name = {name!r} must be an "
                          "identifier (letters, digits, _), e.g. 'periodic_encoder'")
    if name in LIBRARY and LIBRARY[name] is not obj:
        raise EffectError(f"{where}: {spec!r}: name {name!r} is a library effect's; choose "
                          "another name")
    if not isinstance(getattr(obj, "summary", None), str):
        raise EffectError(f"{where}: {spec!r}: needs a class attribute summary = '...' (what "
                          "the effect does)")
    bad = [p for p in obj.parameters if not isinstance(p, Parameter)]
    if bad:
        raise EffectError(f"{where}: {spec!r}: parameters must be Parameter(...) entries, got "
                          f"{bad[0]!r}")
    return obj


class UntrustedEffectError(EffectError):
    """A file names a user effect whose code the user has not consented to run."""


def _code_of(spec: str, base_dir=None) -> str:
    """The code a ``file.py:Class`` or ``module:Class`` spec runs: the file's resolved path, or
    the module's name (a bare ``file.py`` or module names the same code)."""
    target, sep, cls_name = spec.strip().rpartition(":")
    if not (sep and cls_name.isidentifier() and target):
        target = spec.strip()
    if target.endswith(".py") or "/" in target or "\\" in target:
        path = Path(target).expanduser()
        if not path.is_absolute():
            path = Path(base_dir or ".") / path
        return str(path.resolve())
    return target


def _consented(trust, code: str) -> bool:
    """Whether ``trust`` (True, False, or the specs the user gave) lets ``code`` run."""
    if isinstance(trust, bool):
        return trust
    return code in {_code_of(s) for s in trust}


def _load_file(path: Path, cls_name: str, spec: str, where: str) -> type[Effect]:
    path = path.resolve()
    if not path.is_file():
        raise EffectError(f"{where}: {spec!r}: no such file {str(path)!r}")
    # one module per file content: a file edited (or rewritten) in the same session reloads
    digest = hashlib.sha1(str(path).encode() + b"\0" + path.read_bytes()).hexdigest()[:16]
    module_name = f"deltatwin_user_effects.{path.stem}_{digest}"
    module = sys.modules.get(module_name)
    if module is None:
        loader_spec = importlib.util.spec_from_file_location(module_name, path)
        module = importlib.util.module_from_spec(loader_spec)
        try:
            loader_spec.loader.exec_module(module)
        except Exception as exc:
            raise EffectError(f"{_where_in(str(path), exc)}: error while loading {spec!r}: "
                              f"{type(exc).__name__}: {exc}") from exc
        sys.modules[module_name] = module
    if not hasattr(module, cls_name):
        found = [n for n, o in vars(module).items()
                 if isinstance(o, type) and issubclass(o, Effect) and o is not Effect]
        raise EffectError(f"{where}: {spec!r}: {str(path)!r} defines no {cls_name!r}; its "
                          f"effects: {found}")
    cls = _checked(getattr(module, cls_name), spec, where)
    if cls not in _SOURCE:
        _guarded(cls, str(path))
        _SOURCE[cls] = f"{path}:{cls_name}"
    return cls


def _load_module(module_name: str, cls_name: str, spec: str, where: str) -> type[Effect]:
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:
        raise EffectError(f"{where}: {spec!r}: cannot import {module_name!r}: "
                          f"{type(exc).__name__}: {exc}") from exc
    if not hasattr(module, cls_name):
        raise EffectError(f"{where}: {spec!r}: module {module_name!r} defines no {cls_name!r}")
    cls = _checked(getattr(module, cls_name), spec, where)
    if cls not in _SOURCE:
        _guarded(cls, inspect.getsourcefile(cls) or module_name)
        _SOURCE[cls] = f"{module_name}:{cls_name}"
    return cls


def _entry_point(name: str, where: str) -> type[Effect] | None:
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name == name:
            try:
                obj = ep.load()
            except Exception as exc:
                raise EffectError(f"{where}: entry point {name!r} ({ep.value}) of group "
                                  f"{ENTRY_POINT_GROUP!r} fails to load: {type(exc).__name__}: "
                                  f"{exc}") from exc
            cls = _checked(obj, ep.value, where)
            if cls not in _SOURCE:
                _guarded(cls, inspect.getsourcefile(cls) or ep.value)
                _SOURCE[cls] = name if cls.name == name else ep.value
            return cls
    return None


def effect_class(spec, base_dir=None, where: str = "effects", trust=True) -> type[Effect]:
    """The Effect subclass a spec names: a library name, a user effect already resolved (by its
    name), ``file.py:Class`` (relative to ``base_dir``, default the working directory),
    ``module:Class``, an entry point of the ``deltatwin.effects`` group, or an Effect subclass
    itself. Errors name ``where``. ``trust`` (see the module docstring): whether the code of a
    ``file.py:Class`` or ``module:Class`` may run (False: UntrustedEffectError; a collection of
    specs: only their code)."""
    if isinstance(spec, type):
        cls = _checked(spec, getattr(spec, "__name__", str(spec)), where)
        if cls.name not in LIBRARY:
            _USER.setdefault(cls.name, cls)
        return cls
    if not isinstance(spec, str) or not spec.strip():
        raise EffectError(f"{where}: expected an effect name or 'file.py:Class', got {spec!r}")
    spec = spec.strip()
    if spec in LIBRARY:
        return LIBRARY[spec]
    if spec in _USER:
        return _USER[spec]
    target, sep, cls_name = spec.rpartition(":")
    if sep and cls_name.isidentifier() and target:
        code = _code_of(spec, base_dir)
        if not _consented(trust, code):
            raise UntrustedEffectError(
                f"{where}: {spec!r} is a user effect: reading this file would run the Python code "
                f"{code}; refused, as it may do anything. Run it only if you trust it: "
                "--trust-effects (Python: trust_effects=True)")
        if target.endswith(".py") or "/" in target or "\\" in target:
            path = Path(target).expanduser()
            if not path.is_absolute():
                path = Path(base_dir or ".") / path
            cls = _load_file(path, cls_name, spec, where)
        else:
            cls = _load_module(target, cls_name, spec, where)
    else:
        cls = _entry_point(spec, where)
        if cls is None:
            known = sorted(LIBRARY) + sorted(_USER)
            close = difflib.get_close_matches(spec, known, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise EffectError(f"{where}: unknown effect {spec!r}{hint}; known: {known}; your "
                              "own: 'my_effects.py:ClassName' (docs/effects.md)")
    other = _USER.get(cls.name)
    if other is not None and other is not cls and effect_spec(other) != effect_spec(cls):
        raise EffectError(f"{where}: {spec!r}: effect name {cls.name!r} is already taken by "
                          f"{effect_spec(other)!r}")
    _USER[cls.name] = cls
    return cls


def effect_spec(cls: type[Effect]) -> str:
    """How to name ``cls`` again in a file (a fitted model, a scenario): its library name, or
    the absolute 'file.py:Class' / 'module:Class' / entry point it was loaded from."""
    if LIBRARY.get(cls.name) is cls:
        return cls.name
    if cls in _SOURCE:
        return _SOURCE[cls]
    source = inspect.getsourcefile(cls)
    return f"{Path(source).resolve()}:{cls.__qualname__}" if source else cls.name


def code_sha256(classes) -> str | None:
    """A fingerprint of the code that computes these effects (SHA-256, hex): deltatwin's version
    and, per class in order, its name and the source files of it and of every class it inherits
    from below ``Effect`` (mixins too), then the researcher's own modules those files import
    (``_own_modules``: helpers, transitively; sorted by module name). A fitted model keeps it, so
    a diagnosis keeps the values as fitted only when the code that evaluates them is the code
    that fitted them (a researcher's effect or helper edited since the fit is refined, not
    trusted). Where the files lie does not count (a project moved keeps its fingerprint). Not
    covered: installed packages (numpy, scipy, ...) and the kinematics and optics the effects
    build on, covered by the version alone. None (never equal to a file's) when a class's
    source cannot be read (defined in a notebook or a REPL)."""
    from deltatwin import __version__

    h = hashlib.sha256(__version__.encode())
    modules = {}
    for cls in classes:
        h.update(b"\0" + cls.__qualname__.encode())
        for c in cls.__mro__:
            if c is object or c in Effect.__mro__:
                continue
            try:
                h.update(b"\0" + c.__qualname__.encode() + b"\0"
                         + Path(inspect.getsourcefile(c)).read_bytes())
            except (TypeError, OSError):
                return None
            if c.__module__ in sys.modules:
                modules[c.__module__] = sys.modules[c.__module__]
    helpers = {}
    for module in modules.values():
        _own_modules(module, helpers)
    for name in sorted(set(helpers) - set(modules)):
        try:
            h.update(b"\0" + name.encode() + b"\0" + Path(helpers[name]).read_bytes())
        except OSError:
            return None
    return h.hexdigest()


def _own_modules(module, found: dict) -> None:
    """Add to ``found`` ({module name: source file}) the modules ``module``'s source imports
    (anywhere in it, read from the file: ``import a.b``, ``from a import b``, relative
    imports; so a constant or a function imported from a helper counts as the helper) that are
    the researcher's own code, transitively: loaded, and neither deltatwin's (its version covers
    them) nor installed (``_installed``) nor built in. A namespace package has no file of its
    own; its modules count by their own names."""
    try:
        tree = ast.parse(Path(module.__file__).read_bytes())
    except (AttributeError, TypeError, OSError, SyntaxError, ValueError):
        return
    for name in _imported_names(tree, getattr(module, "__package__", None) or ""):
        other = sys.modules.get(name)
        if other is None or name in found or name.split(".")[0] == "deltatwin":
            continue
        source = getattr(other, "__file__", None)
        if not isinstance(source, str) or not source.endswith(".py") or _installed(source):
            continue
        found[name] = source
        _own_modules(other, found)


def _imported_names(tree: ast.AST, package: str):
    """The module names an import statement in ``tree`` may load: every parent of ``import
    a.b.c``, and for ``from m import x`` both ``m`` and ``m.x`` (x may be a submodule)."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                yield from (".".join(parts[:k]) for k in range(1, len(parts) + 1))
        elif isinstance(node, ast.ImportFrom):
            try:
                base = importlib.util.resolve_name("." * node.level + (node.module or ""),
                                                   package) if node.level else node.module
            except (ImportError, ValueError):
                continue
            yield base
            yield from (f"{base}.{alias.name}" for alias in node.names)


@functools.cache
def _installed_roots() -> tuple:
    """Where Python and installed packages lie: the interpreter's own paths, every
    site-packages (the user's too) and any ``site-packages``/``dist-packages`` folder on
    sys.path (Debian's, a PYTHONPATH entry)."""
    import site
    import sysconfig

    paths = sysconfig.get_paths()
    roots = [paths[k] for k in ("stdlib", "platstdlib", "purelib", "platlib")]
    roots += list(getattr(site, "getsitepackages", lambda: [])())
    roots.append(site.getusersitepackages())
    roots += [p for p in sys.path if Path(p).name in ("site-packages", "dist-packages")]
    return tuple({Path(r).resolve() for r in roots if r})


def _installed(source: str) -> bool:
    """Whether the file ``source`` is part of Python or an installed package."""
    resolved = Path(source).resolve()
    return any(resolved.is_relative_to(root) for root in _installed_roots())


def make_effect(spec, values: dict | None = None, where: str = "effects",
                check_minimum: bool = True, base_dir=None, trust=True) -> Effect:
    """The effect ``spec`` names (see ``effect_class``, and its ``trust``) with parameter
    ``values`` (validated; a fitted model's values may be below a parameter's physical minimum
    with ``check_minimum=False``); errors name ``where``."""
    cls = effect_class(spec, base_dir, where, trust)
    return cls(where=f"{where}.{cls.name}", check_minimum=check_minimum, **(values or {}))


__all__ = ["ENTRY_POINT_GROUP", "LIBRARY", "Effect", "EffectError", "Parameter",
           "UntrustedEffectError", "code_sha256", "effect_class", "effect_spec", "make_effect",
           "shift_reading"]
