"""``deltatwin setup DATA [FILE -o OUT]``: the laboratory's setup a dataset carries, shown, or
stated from a setup file (twin/lab_setup.py; docs/data-format.md, docs/lab-setup.toml)."""
from __future__ import annotations

from deltatwin.commands.output import strict_json


def register(sub) -> None:
    p = sub.add_parser("setup", help="show the laboratory's setup a dataset carries, or write "
                                     "the dataset with a setup file's",
                       description="Without FILE: print the setup DATA carries (the known "
                                   "constants, baseline, thermometers and instrument "
                                   "specifications that fit, diagnose and compensate take as "
                                   "given). With FILE (TOML, docs/lab-setup.toml) and -o: "
                                   "write DATA with that setup to OUT; the file is checked "
                                   "first and nothing is written if a key is wrong.")
    p.add_argument("data", help="dataset (.parquet, or .csv with its .meta.json)")
    p.add_argument("setup_file", nargs="?", metavar="FILE",
                   help="the laboratory's setup file (TOML) to put into the dataset")
    p.add_argument("-o", "--output",
                   help="dataset to write with FILE's setup (.parquet or .csv)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args) -> int:
    from deltatwin.twin.dataset import (
        check_dataset_path,
        read_dataset,
        temperature_columns,
        write_dataset,
    )
    from deltatwin.twin.lab_setup import SETUP_KEY, describe, load_setup, with_setup

    if args.setup_file is not None and args.output is None:
        raise ValueError(f"{args.setup_file}: give -o OUT, the dataset to write with this setup")
    if args.setup_file is None and args.output is not None:
        raise ValueError("-o: give the setup FILE to write into the dataset")
    if args.output is not None:
        check_dataset_path(args.output, "-o")
    setup = load_setup(args.setup_file) if args.setup_file is not None else None
    df, meta = read_dataset(args.data)
    if setup is not None:
        meta = with_setup(meta, setup, str(args.setup_file), temperature_columns(df))
        write_dataset(df, meta, args.output)
    shown = {"data": str(args.output or args.data), SETUP_KEY: meta.get(SETUP_KEY),
             "instruments": meta.get("instruments"), "sensors": meta.get("sensors")}
    if args.json:
        print(strict_json(shown))
    else:
        print(f"{shown['data']}: setup: {describe(meta)}")
    return 0
