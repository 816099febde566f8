"""The house: data flows one way (models -> twin -> calibration -> the application), each
layer imports only the ones below it, no module imports a POSIX-only module where a lab PC on
Windows needs it, and importing the package changes no global state."""
import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# folder -> installed package, lowest layer first
LAYERS = {"models": "deltatwin.models", "twin": "deltatwin.twin", "hw": "deltatwin.hw",
          "calibration": "deltatwin.calibration"}
# what each layer may import from the project (besides itself and the ground floor)
ALLOWED = {
    "deltatwin.models": set(),
    "deltatwin.twin": {"deltatwin.models"},
    "deltatwin.hw": {"deltatwin.models", "deltatwin.twin"},
    "deltatwin.calibration": {"deltatwin.models", "deltatwin.twin"},
}
# the package root (its version, lazy API) and the file writers: every layer may use them
GROUND_FLOOR = {"deltatwin", "deltatwin.files", "deltatwin.progress"}


def _project_imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return {m for m in out if m == "deltatwin" or m.startswith("deltatwin.")}


@pytest.mark.parametrize("folder", LAYERS)
def test_each_layer_imports_only_the_layers_below(folder):
    package = LAYERS[folder]
    offending = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        for module in _project_imports(path):
            if module.startswith(package) or module in GROUND_FLOOR:
                continue
            if not any(module == a or module.startswith(a + ".") for a in ALLOWED[package]):
                offending.append(f"{path.relative_to(ROOT)} imports {module}")
    assert not offending, "\n".join(offending)


def test_calibration_paths_do_not_import_each_other():
    """The black-box path and the physics path are independent; the diagnosis joins them."""
    for a, b in (("blackbox", "physics"), ("physics", "blackbox"), ("blackbox", "diagnosis"),
                 ("physics", "diagnosis")):
        for path in (ROOT / "calibration" / a).rglob("*.py"):
            bad = [m for m in _project_imports(path)
                   if m.startswith(f"deltatwin.calibration.{b}")]
            assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_nothing_imports_the_commands():
    for folder in [*LAYERS, "deltatwin"]:
        for path in (ROOT / folder).rglob("*.py"):
            if "commands" in path.parts or path.name in ("cli.py", "__main__.py"):
                continue
            bad = [m for m in _project_imports(path) if m.startswith("deltatwin.commands")
                   or m == "deltatwin.cli"]
            assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def _all_modules() -> list[str]:
    mods = []
    for folder, package in {**LAYERS, "deltatwin": "deltatwin"}.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            if parts[-1:] == ["__main__"]:
                continue
            mods.append(".".join([package, *parts]))
    return mods


def test_every_module_imports_without_posix_only_modules():
    """termios, tty and fcntl do not exist on Windows: no module may need them to import."""
    # pyserial picks its own backend per platform (serialwin32 on Windows): import it first
    code = ("import sys, serial\n"
            "for name in ('termios', 'tty', 'fcntl'):\n"
            "    sys.modules[name] = None      # import raises ImportError, as on Windows\n"
            "import importlib\n"
            f"for m in {_all_modules()!r}:\n"
            "    importlib.import_module(m)\n"
            "print('ok')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]


def test_importing_the_package_loads_nothing_heavy_and_prints_nothing():
    code = ("import sys, matplotlib\n"
            "backend = matplotlib.get_backend()\n"
            "import deltatwin as dt\n"
            "heavy = [m for m in ('numpy', 'mujoco', 'scipy', 'pandas', 'rerun') if m in sys.modules"
            " and m != 'numpy']\n"
            "assert not heavy, heavy\n"
            "dt.PhysicsFit, dt.Scenario, dt.diagnose, dt.DGM, dt.write_recording\n"
            "import deltatwin.calibration.diagnosis.report\n"
            "assert matplotlib.get_backend() == backend, (backend, matplotlib.get_backend())\n")
    # a notebook's backend, stood in for by svg: writing reports must not switch it to Agg
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "MPLBACKEND": "svg"})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout == "", f"importing printed {r.stdout!r}"


def test_the_public_api_names_resolve():
    import deltatwin as dt
    for name in dt.__all__:
        assert getattr(dt, name) is not None, name
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        dt.Nope  # noqa: B018


def test_every_package_folder_is_installed():
    """A new subpackage must be listed in pyproject.toml, or the wheel silently lacks it."""
    import tomllib
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(config["packages"])
    for folder, package in {**LAYERS, "deltatwin": "deltatwin", "scenarios": "deltatwin.scenarios"}.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            name = ".".join([package, *rel])
            assert name in listed, f"{init.parent.relative_to(ROOT)}: {name} not in pyproject packages"


DIAGNOSIS_FUNCTION_LINES = 80


def test_every_function_of_the_diagnosis_reads_at_once():
    """No function (or method) of calibration/diagnosis/ is longer than 80 lines, its docstring
    included: a maintainer reads each at once."""
    long = []
    for path in sorted((ROOT / "calibration" / "diagnosis").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > DIAGNOSIS_FUNCTION_LINES:
                    long.append(f"{path.name}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, long


def test_no_private_name_is_imported_across_modules():
    """A name with a leading underscore belongs to its module: no module of the package imports
    one from another (a shared helper is public in the one place it lives)."""
    crossing = []
    for folder in (*LAYERS, "deltatwin"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("deltatwin"):
                    crossing += [f"{path.relative_to(ROOT)}: {node.module}.{a.name}"
                                 for a in node.names
                                 if a.name.startswith("_") and not a.name.startswith("__")]
    assert not crossing, crossing
