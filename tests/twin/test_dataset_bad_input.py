"""Bad datasets, as laboratory files go wrong: each is refused naming the file and the column
or row (a DatasetError), never read silently or with a vague message."""
import json

import numpy as np
import pandas as pd
import pytest

from deltatwin.twin.dataset import DatasetError, read_dataset, write_dataset


def _table(n=12):
    rng = np.random.default_rng(3)
    return pd.DataFrame({
        "t_s": np.arange(n) * 10.0, "pos_id": np.arange(n) // 2,
        "split": ["cal"] * (n // 2) + ["val"] * (n - n // 2), "session": "xy",
        "q1_rad": rng.uniform(-0.05, 0.05, n), "q2_rad": rng.uniform(-0.05, 0.05, n),
        "q3_rad": rng.uniform(-0.05, 0.05, n), "x_nm": rng.normal(0, 50, n),
        "y_nm": rng.normal(0, 50, n), "T_base_C": 20 + rng.normal(0, 0.01, n)})


def _csv(tmp_path, df, meta=None):
    path = tmp_path / "lab.csv"
    write_dataset(df, meta or {"source": "lab"}, path)
    return path


def _edit_csv(path, edit):
    path.write_text(edit(path.read_text()))


CASES = {
    "duplicated rows": (lambda df: pd.concat([df, df.iloc[:3]], ignore_index=True), None,
                        "repeat an earlier row"),
    "inf reading": (lambda df: df.assign(x_nm=df.x_nm.where(df.index != 4, np.inf)), None,
                    "x_nm"),
    "axis in micrometres": (lambda df: df.rename(columns={"x_nm": "x_um"}), None, "x_um"),
    "reading 1e300": (lambda df: df.assign(y_nm=df.y_nm.where(df.index != 2, 1e300)), None,
                      "y_nm"),
    "text in a reading": (lambda df: df.assign(x_nm=df.x_nm.astype(object).where(
        df.index != 5, "12,5")), None, "x_nm"),
    "temperature 1e6": (lambda df: df.assign(T_base_C=1e6), None, "T_base_C"),
    "cut mid-line": (None, lambda p: _edit_csv(p, lambda t: t[:-7]), "incomplete"),
    "metadata a JSON list": (None, lambda p: p.with_suffix(".meta.json").write_text("[1, 2]"),
                             "meta.json"),
    "corrupt sidecar": (None, lambda p: p.with_suffix(".meta.json").write_text("{not json"),
                        "meta.json"),
    "sidecar of another version": (None, lambda p: _edit_csv(
        p, lambda t: t.replace("\n", "\n", 1)[:-1] + "0\n"), "another version"),
    "future format": (None, lambda p: p.with_suffix(".meta.json").write_text(
        json.dumps({"format_version": 99})), "format_version"),
    "missing column": (lambda df: df.drop(columns=["q2_rad"]), None, "q2_rad"),
    "pressure in hPa": (lambda df: df.assign(p_Pa=1013.25), None, "p_Pa"),
    "humidity above 100 %": (lambda df: df.assign(RH_pct=42.0 + 100.0 * (df.index == 3)), None,
                             "RH_pct"),
    "humidity as text": (lambda df: df.assign(RH_pct=np.where(df.index == 1, "45 %", "45")),
                         None, "RH_pct"),
}


@pytest.mark.parametrize("case", CASES)
def test_bad_dataset_is_refused_naming_what_and_where(case, tmp_path):
    change_table, change_file, needle = CASES[case]
    df = _table()
    if change_table is not None:
        df = change_table(df)
        path = tmp_path / "lab.csv"
        df.to_csv(path, index=False)              # as a laboratory writes it, no checks
    else:
        path = _csv(tmp_path, df)
        change_file(path)
    with pytest.raises(DatasetError) as err:
        read_dataset(path)
    # the file at fault is named: the CSV, or its sidecar lab.meta.json
    assert str(tmp_path / "lab.") in str(err.value) and needle in str(err.value), str(err.value)


def test_a_folder_is_not_a_dataset(tmp_path):
    with pytest.raises(DatasetError, match="folder"):
        read_dataset(tmp_path)


def test_a_written_pair_reads_back(tmp_path):
    df = _table()
    back, meta = read_dataset(_csv(tmp_path, df, {"source": "lab", "seed": 4}))
    assert meta["seed"] == 4 and len(back) == len(df)
    np.testing.assert_allclose(back["x_nm"], df["x_nm"], rtol=1e-9)
