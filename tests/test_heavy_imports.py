"""A library module imports a heavy dependency only where it is used (issue 21): fitting a
physics model loads neither scipy.signal (the thermal network's filter) nor scipy.stats,
statsmodels, trimesh or MuJoCo; the stepwise regression loads no scipy.stats."""
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
