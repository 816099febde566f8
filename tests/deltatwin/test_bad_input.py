"""Bad input on the command line ends in one line naming what and where, exit 2, and leaves
nothing written: campaign scales, dataset suffixes, --set typos, a missing model file, an
interrupted demo; and the demo names the scenario file it runs."""
import pytest

from deltatwin.cli import main
from deltatwin.twin.effects import HOOKS, Effect


def error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


@pytest.fixture(scope="module")
def force_data(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "force.parquet"
    assert main(["simulate", "paper-force", "--scale", "0.1", "--no-floor", "-q",
                 "-o", str(path)]) == 0
    return path


@pytest.mark.parametrize("command", ["simulate", "emulate", "campaign"])
@pytest.mark.parametrize("scale", ["-0.5", "0", "nan", "inf", "5"])
def test_a_scale_outside_0_1_is_refused_before_anything_runs(tmp_path, capsys, command, scale):
    argv = [command, "paper-force", f"--scale={scale}"]
    argv += [] if command == "emulate" else ["-o", str(tmp_path / "d.parquet")]
    argv += ["--instruments", "sim"] if command == "campaign" else []
    assert main(argv) == 2
    line = error_line(capsys)
    assert f"--scale = {float(scale)}" in line and "0 < SCALE <= 1" in line, line
    assert list(tmp_path.iterdir()) == []


def test_the_help_states_the_accepted_scale(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    assert "0 < SCALE <= 1" in capsys.readouterr().out


@pytest.mark.parametrize("name", ["out.txt", "out", "out.PARQUET.gz"])
def test_an_unknown_dataset_suffix_is_refused_not_written_as_parquet(tmp_path, capsys, name):
    assert main(["simulate", "paper-force", "--scale", "0.05", "--no-floor", "-q",
                 "-o", str(tmp_path / name)]) == 2
    line = error_line(capsys)
    assert name in line and ".parquet or .csv" in line, line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("setting, words", [
    ("loop_drfit.frame_arm_m=-0.6,0", ["--set loop_drfit.frame_arm_m=-0.6,0",
                                       "did you mean 'loop_drift'", "geometric_errors"]),
    ("loop_drift.frame_arm=-0.6,0", ["--set loop_drift.frame_arm=-0.6,0",
                                     "did you mean 'frame_arm_m'", "frame_height_m"]),
    ("loop_drift.frame_arm_m=1", ["--set loop_drift.frame_arm_m=1", "shape (2,)"]),
])
def test_a_set_typo_is_named_as_the_user_wrote_it(force_data, capsys, setting, words):
    assert main(["fit", str(force_data), "--effects", "geometric_errors", "--set", setting,
                 "--json"]) == 2
    line = error_line(capsys)
    assert "--effects." not in line and "known constants" not in line, line
    for w in words:
        assert w in line, (w, line)


@pytest.mark.parametrize("name", ["nope.toml", "nope.json"])
def test_diagnose_a_missing_model_file_is_one_clear_line(force_data, tmp_path, capsys, name):
    assert main(["diagnose", str(force_data), "--model", str(tmp_path / name)]) == 2
    line = error_line(capsys)
    assert f"{tmp_path / name}: no such model file" in line and "Errno" not in line, line


def test_every_hook_of_an_effect_is_guarded():
    """A user effect's exception in any stage hook (motor_angles too) names its file and line."""
    hooks = {n for n, v in vars(Effect).items() if callable(v) and not n.startswith("_")
             and not isinstance(v, classmethod)} - {"outside_range", "describe"}
    assert hooks == set(HOOKS)


def _interrupt_the_ladder(monkeypatch):
    import deltatwin.calibration.diagnosis.diagnose as diagnose

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(diagnose, "effect_ladder", interrupted)


def test_an_interrupted_demo_leaves_no_half_filled_folder(tmp_path, monkeypatch, capsys):
    """Interrupted once the dataset is written: neither the folder asked for nor a temporary
    one is left; a previous run's folder is left as it was. The demo names the scenario file
    it runs (quiet/magnetic-force, whose [scenario] name is hidden-magnetic-force)."""
    _interrupt_the_ladder(monkeypatch)
    out = tmp_path / "run"
    assert main(["demo", "--out", str(out), "--scale", "0.05", "--no-recording"]) == 130
    err = capsys.readouterr().err
    assert "simulating quiet/magnetic-force " in err and "hidden-magnetic-force" not in err
    assert f"{out / 'data.parquet'}" in err            # the final path, not the temporary one
    assert list(tmp_path.iterdir()) == []
    out.mkdir()
    (out / "report.md").write_text("the previous run")
    assert main(["demo", "--out", str(out), "--scale", "0.05", "--no-recording", "-q"]) == 130
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    assert [p.name for p in out.iterdir()] == ["report.md"]
    assert (out / "report.md").read_text() == "the previous run"
