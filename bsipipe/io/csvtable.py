"""Write result tables as CSV, byte for byte what ``DataFrame.to_csv`` writes, faster.

``pandas.DataFrame.to_csv`` formats every cell through several Python layers (about 15 us a
cell): the 2-D table of a 2,000-frame, two-view track (48,000 rows, 20 columns) took about a
second.  :func:`write_csv` formats whole columns at once (``float_format % v`` over a list,
integers and booleans by ``str``) and joins the rows, for the tables bsipipe writes: the
columns are floats, integers, booleans and strings, no index.  For anything else (a
callable or missing ``float_format``, an index, a non-default separator, quoting or date
format, a column holding other objects) it hands the frame to pandas, so the output is
always pandas' own.

>>> import pandas as pd
>>> df = pd.DataFrame({"a": [1.5, float("nan")], "b": ["x", 'say "hi", then go'], "c": [True, False]})
>>> write_csv(df, float_format="%.2f", na_rep="") == df.to_csv(index=False, float_format="%.2f", na_rep="")
True
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np
import pandas as pd

#: ``to_csv`` keywords :func:`write_csv` formats itself (with these values); any other makes it call pandas.
_OWN = {"index": False, "lineterminator": None, "float_format": None, "na_rep": None, "encoding": "utf-8"}


def _quoted(s: str, end: str = "\n") -> str:
    """A field as the csv module's ``QUOTE_MINIMAL`` writes it (pandas' default): quoted
    when it holds the separator, the quote or a character of the line terminator ``end``."""
    if "," in s or '"' in s or any(c in s for c in end):
        return '"' + s.replace('"', '""') + '"'
    return s


def _is_na(v) -> bool:
    return v is None or (isinstance(v, float) and v != v) or v is pd.NA


def _column(a: np.ndarray, float_format: str, na_rep: str, end: str) -> list[str] | None:
    """The column's fields, or None where pandas must format it."""
    kind = a.dtype.kind
    if kind == "f":
        s = [float_format % v for v in a.tolist()]
        for i in np.flatnonzero(np.isnan(a)).tolist():
            s[i] = na_rep
        return s
    if kind in "iu":
        return list(map(str, a.tolist()))
    if kind == "b":
        return ["True" if v else "False" for v in a.tolist()]
    if kind in "OUT":
        out = []
        for v in a.tolist():
            if isinstance(v, str):
                out.append(_quoted(v, end))
            elif _is_na(v):
                out.append(na_rep)
            else:                       # numbers or objects inside an object column: pandas' rules
                return None
        return out
    return None


def _own_kind(a: np.ndarray) -> bool:
    """Whether :func:`_column` formats this column (every part of it)."""
    kind = a.dtype.kind
    if kind in "fiub":
        return True
    return kind in "OUT" and all(isinstance(v, str) or _is_na(v) for v in a.tolist())


#: Rows formatted at a time: the formatted fields of a block are Python strings (about 60 bytes
#: each), so a whole long table at once would hold tens of MB of them.
CHUNK_ROWS = 8192


def write_csv(df: pd.DataFrame, f=None, **kw: Any) -> str | None:
    """``df.to_csv(f, **kw)`` with the same bytes: text if ``f`` is None, else written to the
    file object ``f`` (text or binary; binary is UTF-8), :data:`CHUNK_ROWS` rows at a time."""
    own = set(kw) <= set(_OWN) and kw.get("index", False) is False and kw.get("encoding", "utf-8") == "utf-8" \
        and isinstance(kw.get("float_format"), str) and isinstance(df.columns, pd.Index) \
        and not isinstance(df.columns, pd.MultiIndex)
    arrays = [df[c].to_numpy() for c in df.columns] if own else []
    if not own or not all(_own_kind(a) for a in arrays):
        return df.to_csv(f, **kw)
    ff, na = kw["float_format"], kw.get("na_rep", "") or ""
    end = kw.get("lineterminator") or "\n"
    head = ",".join(_quoted(str(c), end) for c in df.columns)
    lone = len(df.columns) == 1         # the csv module quotes a lone empty field
    if lone:
        head = head or '""'
    buf = io.StringIO() if f is None else None

    def put(text: str) -> None:
        if buf is not None:
            buf.write(text)
        elif isinstance(f, io.TextIOBase):
            f.write(text)
        else:
            f.write(text.encode("utf-8"))

    put(head + end)
    for i in range(0, len(df), CHUNK_ROWS):
        cols = [_column(a[i:i + CHUNK_ROWS], ff, na, end) for a in arrays]
        if lone:
            cols = [['""' if v == "" else v for v in cols[0]]]
        put("".join([",".join(r) + end for r in zip(*cols)]))
    return buf.getvalue() if buf is not None else None
