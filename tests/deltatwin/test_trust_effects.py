"""A scenario or a fitted model naming a user effect (file.py:Class) does not run its code unless
the user consents: --trust-effects (every one), --trust-effects SPEC (that code only), or
trust_effects= in Python. The refusal is one line naming the file and the code, exit 2; the
code has not run (its import would write a marker file)."""
import re

import pytest

from deltatwin.calibration.errors import FitError
from deltatwin.calibration.physics.fit import PhysicsFit
from deltatwin.calibration.physics.model_file import fitted_toml, load_fitted
from deltatwin.cli import main
from deltatwin.twin.dataset import write_dataset
from deltatwin.twin.scenario import SCENARIO_DIR, Scenario, ScenarioError
from tests.user_effect_files import marker_effect_file


def error_line(capsys) -> str:
    """The one error line on stderr (progress lines aside), no traceback."""
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if ": error: " in x]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _lab(tmp_path, tag, cls="Ripple"):
    """A user effect file and a scenario naming it (relative to the scenario's folder)."""
    (tmp_path / f"fx_{tag}.py").write_text(marker_effect_file(f"ripple_{tag}", f"angles_{tag}"))
    text = (SCENARIO_DIR / "paper-force.toml").read_text()
    text = re.sub(r"(?m)^on = \[", f'on = ["./fx_{tag}.py:{cls}", ', text, count=1)
    (tmp_path / "lab.toml").write_text(text)
    return tmp_path / "lab.toml", (tmp_path / f"fx_{tag}.py").resolve()


def test_a_scenario_naming_a_user_effect_is_refused_without_consent(tmp_path, capsys):
    scenario, code = _lab(tmp_path, "s")
    assert main(["simulate", str(scenario), "--scale", "0.05", "--no-floor",
                 "-o", str(tmp_path / "d.parquet")]) == 2
    line = error_line(capsys)
    assert str(scenario) in line and str(code) in line and "--trust-effects" in line, line
    assert not (tmp_path / "ran.txt").exists() and not (tmp_path / "d.parquet").exists()
    with pytest.raises(ScenarioError, match="trust_effects=True"):
        Scenario.load(scenario)
    assert not (tmp_path / "ran.txt").exists()
    # consent: the flag, or the flag naming this very file (its path as the user gives it)
    assert main(["simulate", str(scenario), "--scale", "0.05", "--no-floor", "-q",
                 "--trust-effects", "-o", str(tmp_path / "d.parquet")]) == 0
    assert (tmp_path / "ran.txt").exists()
    assert [e.name for e in Scenario.load(scenario, trust_effects=[f"{code}:Ripple"]).effects][0] \
        == "ripple_s"
    with pytest.raises(ScenarioError, match="would run the Python code"):
        Scenario.load(scenario, trust_effects=[str(tmp_path / "other.py")])


def test_a_model_file_naming_a_user_effect_is_refused_without_consent(tmp_path, capsys):
    scenario, code = _lab(tmp_path, "m")
    sc = Scenario.load(scenario, trust_effects=True)
    df, meta = sc.simulate(0.05)
    data = tmp_path / "d.parquet"
    write_dataset(df, meta, data)
    fit = PhysicsFit(["geometric_errors", f"{code}:Ripple"]).fit(df, meta)
    model = tmp_path / "fitted.toml"
    model.write_text(fitted_toml(fit, str(data)))
    with pytest.raises(FitError, match=re.escape(str(code))):
        load_fitted(model)
    load_fitted(model, trust_effects=True)
    for argv in (["compare", str(data), "--model", str(model)],
                 ["diagnose", str(data), "--model", str(model), "--json"],
                 ["view", str(data), "--model", str(model), "-o", str(tmp_path / "r.rrd")]):
        assert main(argv) == 2, argv
        line = error_line(capsys)
        assert str(model) in line and str(code) in line and "content_sha256" not in line, line
    assert main(["compare", str(data), "--model", str(model), "--trust-effects",
                 str(code)]) == 0
    assert "ripple_m" in capsys.readouterr().out


def test_a_damaged_model_file_no_longer_suggests_removing_its_checksum(tmp_path):
    scenario, code = _lab(tmp_path, "c")
    df, meta = Scenario.load("paper-force").simulate(0.05)
    model = tmp_path / "fitted.toml"
    model.write_text(fitted_toml(PhysicsFit(["geometric_errors"]).fit(df, meta), "d.parquet")
                     .replace("noise_nm = 5.0", "noise_nm = 6.0"))
    with pytest.raises(FitError, match="does not match") as err:
        load_fitted(model)
    assert "content_sha256 line" not in str(err.value) and "remove" not in str(err.value)


def test_a_user_effect_raising_in_motor_angles_is_one_line(tmp_path, capsys):
    scenario, code = _lab(tmp_path, "a", "Angles")
    assert main(["simulate", str(scenario), "--scale", "0.05", "--no-floor", "--trust-effects",
                 "-o", str(tmp_path / "d.parquet")]) == 2
    line = error_line(capsys)
    assert f"{code}:" in line and "stage 'motor_angles'" in line and "no encoder" in line, line
    assert not (tmp_path / "d.parquet").exists()
