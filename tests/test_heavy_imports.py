"""A library module imports a heavy dependency only where it is used: fitting a
physics model loads neither scipy.signal nor scipy.stats, statsmodels, trimesh or MuJoCo; the
stepwise regression loads no scipy.stats; simulating a campaign (the thermal network's and the
room's first-order filters) loads neither scipy.signal nor scipy.stats."""
import subprocess
import sys

import pytest

HEAVY = ("scipy.signal", "scipy.stats", "statsmodels", "trimesh", "mujoco")


@pytest.mark.parametrize("modules", [
    ("deltatwin.calibration.physics.fit", "deltatwin.calibration.physics.measurements",
     "deltatwin.twin.world", "deltatwin.twin.campaign", "deltatwin.calibration.diagnosis.diagnose"),
    ("deltatwin.calibration.blackbox.stepwise", "deltatwin.calibration.blackbox.dgm"),
])
def test_importing_loads_no_heavy_dependency(modules):
    code = ("import importlib, sys\n"
            f"for m in {modules!r}:\n"
            "    importlib.import_module(m)\n"
            f"print([h for h in {HEAVY!r} if h in sys.modules])\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "[]", r.stdout


@pytest.mark.parametrize("scenario", ["quiet/magnetic-force", "paper-thermal"])
def test_simulating_loads_no_scipy_signal(scenario):
    """The thermal network and the room climate's filters are twin/thermal.py's
    ``first_order_filter``: scipy.signal (with the scipy.stats it loads, ~0.33 s) stays out."""
    code = ("import sys\n"
            "from deltatwin.twin.scenario import Scenario\n"
            f"Scenario.load({scenario!r}).simulate(0.02)\n"
            "print([h for h in ('scipy.signal', 'scipy.stats') if h in sys.modules])\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "[]", r.stdout
