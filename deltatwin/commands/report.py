"""``deltatwin report``: figures and tables of models on a dataset, laboratory data as the
twin's (calibration/diagnosis/model_report.py, figures.py).

    deltatwin report DATA --model A.toml [--model B.json ...] -o FOLDER

writes FOLDER/report.md and report.html with PNG figures: the error per axis against the floor
the data carry, the residual per axis against time and against the variables it depends on,
maps over the workspace, the residual's distribution, and each model's parameter table (and
its parameters' correlation). The folder is written whole or not at all.
"""
from __future__ import annotations

from pathlib import Path

from deltatwin.commands.trust import add_trust_option, trust_of


def register(sub) -> None:
    p = sub.add_parser("report", help="write a report (Markdown, HTML, PNG figures) of models on "
                                      "a dataset")
    p.add_argument("data", metavar="DATA", help="dataset file (.parquet, or .csv + .meta.json)")
    p.add_argument("--model", action="append", required=True, metavar="MODEL",
                   help="a fitted physics model (.toml from 'deltatwin fit -o') or a DGM (.json "
                        "from 'deltatwin calibrate -o'); repeat for several, in ladder order")
    p.add_argument("-o", "--out", required=True, metavar="FOLDER",
                   help="the report's folder (new, empty, or a previous report's, replaced whole)")
    p.add_argument("--params", metavar="PARAMS.toml",
                   help="robot parameters placing a DGM's positions (default: nominal)")
    add_trust_option(p)
    p.set_defaults(func=run)


def check_report_folder(path) -> Path:
    """The report replaces its folder whole: a folder that holds anything but a previous
    report (no report.md) is refused (FileExistsError), never emptied."""
    path = Path(path)
    if path.is_dir() and any(path.iterdir()) and not (path / "report.md").is_file():
        raise FileExistsError(f"{path}: a folder that holds other files (no report.md): the "
                              "report replaces its folder whole; give a new or empty folder")
    return path


def model_names(paths) -> list[str]:
    """Each model file's name in the report: its stem, numbered where two are the same."""
    stems = [Path(p).stem for p in paths]
    return [s if stems.count(s) == 1 else f"{s} ({k + 1})" for k, s in enumerate(stems)]


def write_report_folder(folder, data: str, df, meta, model_paths, trust=False,
                        params=None) -> Path:
    """Read the models, write the report into ``folder`` (whole or not at all); returns the
    path of report.md under ``folder``."""
    from deltatwin.calibration.diagnosis.model_report import (
        read_model,
        report_model,
        write_model_report,
    )
    from deltatwin.files import atomic_folder

    folder = check_report_folder(folder)
    models = [report_model(name, read_model(path, trust), df, meta, str(path), params)
              for name, path in zip(model_names(model_paths), model_paths)]
    with atomic_folder(folder) as out:
        name = write_model_report(out, df, meta, models, str(data)).name
    return folder / name


def run(args) -> int:
    from deltatwin.twin.dataset import read_dataset

    check_report_folder(args.out)
    df, meta = read_dataset(args.data)
    path = write_report_folder(args.out, args.data, df, meta, args.model, trust_of(args),
                               args.params)
    figures = ", ".join(sorted(p.name for p in path.parent.glob("*.png")))
    print(f"report: {path} (and report.html; figures: {figures})")
    return 0
