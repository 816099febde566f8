"""``deltatwin report`` (and ``compare --report``) on a laboratory's data: a campaign of two
sessions with no truth in its metadata, a physics model and a stepwise DGM; and its bad input,
refused in one line with nothing written."""
import json
import re

import pytest

from deltatwin.cli import main
from deltatwin.twin.dataset import read_dataset, write_dataset

PNG = b"\x89PNG\r\n\x1a\n"


def error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """paper-thermal at 3 % (sessions xy then z) with its truth removed, as a laboratory's
    file; a physics model and a DGM fitted to it; a direct IGM (not a reading's model)."""
    d = tmp_path_factory.mktemp("lab")
    assert main(["simulate", "paper-thermal", "--scale", "0.03", "--no-floor", "-q",
                 "-o", str(d / "twin.parquet")]) == 0
    df, meta = read_dataset(d / "twin.parquet")
    meta.pop("truth")
    write_dataset(df, meta, d / "lab.parquet")
    assert main(["fit", str(d / "lab.parquet"), "--effects", "geometric_errors,thermal_expansion",
                 "-q", "--json", "-o", str(d / "physics.toml")]) == 0
    assert main(["calibrate", str(d / "lab.parquet"), "--features", "thermal", "--sensors",
                 "base,arm1,rod1", "--json", "-o", str(d / "dgm.json")]) == 0
    return d


@pytest.mark.slow
def test_the_report_of_two_models_on_laboratory_data(lab, capsys):
    capsys.readouterr()
    out = lab / "report"
    assert main(["report", str(lab / "lab.parquet"), "--model", str(lab / "physics.toml"),
                 "--model", str(lab / "dgm.json"), "-o", str(out)]) == 0
    assert "report.md" in capsys.readouterr().out
    text = (out / "report.md").read_text()
    shown = re.findall(r"!\[[^]]*\]\(([^)]+\.png)\)", text)
    assert set(shown) == {p.name for p in out.glob("*.png")} == {
        "ladder.png", "residual_time.png", "residual_vs.png", "distribution.png",
        "workspace_1.png", "workspace_2.png", "workspace_compare.png", "correlation_1.png"}
    assert all((out / name).read_bytes()[:8] == PNG for name in shown)
    assert "carry no floor" in text and "2 session(s) (xy, z)" in text
    # the physics model's parameter table (with units) and the DGM's terms (with p-values)
    assert "| geometric_errors.arm_length_error_m[0] |" in text and "| m |" in text
    assert "p-value" in text and "DGM output z (m)" in text
    html = (out / "report.html").read_text()
    assert html.count("<img ") == len(shown) and "<table>" in html
    # written again over itself: a previous report's folder is replaced whole
    (out / "stale.png").write_bytes(PNG)
    assert main(["report", str(lab / "lab.parquet"), "--model", str(lab / "dgm.json"),
                 "-o", str(out)]) == 0
    assert not (out / "stale.png").exists() and not (out / "workspace_2.png").exists()


@pytest.mark.slow
def test_compare_writes_the_report_of_its_model(lab, capsys):
    capsys.readouterr()
    out = lab / "compared"
    assert main(["compare", str(lab / "lab.parquet"), "--model", str(lab / "physics.toml"),
                 "--json", "--report", str(out)]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["report"] == str(out / "report.md") and (out / "workspace_1.png").is_file()


def test_bad_input_is_one_line_and_writes_nothing(lab, tmp_path, capsys):
    data, model = str(lab / "lab.parquet"), str(lab / "physics.toml")
    out = tmp_path / "out"
    cases = [
        ([str(tmp_path / "none.parquet"), "--model", model, "-o", str(out)], "none.parquet"),
        ([data, "--model", str(tmp_path / "none.toml"), "-o", str(out)], "no such model file"),
        ([data, "--model", str(tmp_path / "model.txt"), "-o", str(out)],
         "unknown model file type"),
    ]
    for argv, words in cases:
        assert main(["report", *argv]) == 2, argv
        line = error_line(capsys)
        assert words in line, line
        assert not out.exists()
    # -o a file, or a folder under a file: refused before computing, the file untouched
    target = tmp_path / "notes.txt"
    target.write_text("mine")
    for where in (target, target / "report"):
        assert main(["report", data, "--model", model, "-o", str(where)]) == 2
        assert "is a file" in error_line(capsys)
    assert target.read_text() == "mine"
    # a folder of other files is never emptied
    folder = tmp_path / "work"
    folder.mkdir()
    (folder / "data.csv").write_text("1,2\n")
    assert main(["report", data, "--model", model, "-o", str(folder)]) == 2
    assert "no report.md" in error_line(capsys)
    assert [p.name for p in folder.iterdir()] == ["data.csv"]
    assert main(["compare", data, "--model", model, "--report", str(folder)]) == 2
    assert "no report.md" in error_line(capsys)


def test_an_interrupted_report_leaves_no_folder(lab, tmp_path, monkeypatch, capsys):
    from deltatwin.calibration.diagnosis import model_report

    calls = []

    def interrupted(fig, path):
        calls.append(path)
        raise KeyboardInterrupt

    monkeypatch.setattr(model_report, "save_figure", interrupted)
    out = tmp_path / "out"
    assert main(["report", str(lab / "lab.parquet"), "--model", str(lab / "dgm.json"),
                 "-o", str(out)]) == 130
    assert calls and not out.exists() and not list(tmp_path.iterdir())
