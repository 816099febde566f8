"""Result tables as researchers read them (statsmodels' ``Summary``, MATLAB's ``stepwisefit``
display): one object with a text form (``str``), an HTML form (``_repr_html_``, which Jupyter
shows), a Markdown form (a report's) and a JSON-ready form (``as_dict``). Shared by the
black-box and the physics paths."""
from __future__ import annotations

import html
import json
import math


def plain(obj):
    """``obj`` JSON-ready: dicts, lists and tuples walked, numpy values as plain numbers and
    lists, non-finite floats as None (a figure that does not exist)."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):   # numpy scalar or array
        return plain(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def strict_json(obj, indent: int | None = None, **kwargs) -> str:
    """``obj`` as strict JSON text (RFC 8259: no NaN or Infinity; ``plain``)."""
    return json.dumps(plain(obj), indent=indent, allow_nan=False, **kwargs)


def number(x) -> str:
    """A value in a table: 4 significant digits (exponent form outside 1e-4 .. 1e4), '-' for
    a value that does not exist."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.4g}"


class Table:
    """``headings`` (column titles, units in them or in a unit column), ``records`` (one
    JSON-ready dict per row) and ``cells`` (a function giving a record's cells as text, in
    ``headings`` order)."""

    def __init__(self, title: str, headings, records: list[dict], cells):
        self.title = title
        self.headings = tuple(headings)
        self.records = records
        self.cells = cells

    def __len__(self) -> int:
        return len(self.records)

    def rows(self) -> list[list[str]]:
        return [self.cells(r) for r in self.records]

    def __str__(self) -> str:
        return text_table(self.title, self.headings, self.rows())

    def _repr_html_(self) -> str:
        esc = html.escape
        head = "".join(f"<th>{esc(h)}</th>" for h in self.headings)
        body = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>"
                       for r in self.rows())
        return (f"<table><caption>{esc(self.title)}</caption><thead><tr>{head}</tr></thead>"
                f"<tbody>{body}</tbody></table>")

    def markdown(self) -> str:
        lines = ["| " + " | ".join(self.headings) + " |", "|" + "---|" * len(self.headings)]
        lines += ["| " + " | ".join(c.replace("|", "\\|") for c in r) + " |"
                  for r in self.rows()]
        return "\n".join(lines)

    def as_dict(self) -> list[dict]:
        """JSON-ready: one dict per row."""
        return [dict(r) for r in self.records]

    def to_frame(self, index: str | None = None):
        """A pandas DataFrame of the records (indexed by the ``index`` column if given)."""
        import pandas as pd

        frame = pd.DataFrame(self.records)
        return frame.set_index(index) if index else frame


def text_table(title: str, headings, rows: list[list[str]]) -> str:
    """A plain-text table: a title, headings between rules, one line per row; the first
    column left-aligned, the others right-aligned."""
    widths = [max([len(h)] + [len(r[k]) for r in rows]) for k, h in enumerate(headings)]

    def line(cells):
        return "  ".join(c.ljust(w) if k == 0 else c.rjust(w)
                         for k, (c, w) in enumerate(zip(cells, widths))).rstrip()

    rule = "-" * sum(w + 2 for w in widths)
    return "\n".join([title, rule, line(headings), rule, *map(line, rows), rule])
