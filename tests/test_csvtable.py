"""bsipipe.io.csvtable.write_csv writes the bytes pandas' to_csv writes."""

import io

import numpy as np
import pandas as pd
import pytest

from bsipipe.io import csvtable
from bsipipe.io.csvtable import write_csv

AWKWARD = ["", "plain", "a,b", 'say "hi"', "two\nlines", "cr\rx", " lead", "tab\tx", "é ü", "NaN", "-0"]


def _frame(rng: np.random.Generator, n: int) -> pd.DataFrame:
    f = rng.normal(0, 10 ** rng.uniform(-8, 8, n), n)
    f[rng.random(n) < 0.2] = np.nan
    f[rng.random(n) < 0.05] = np.inf * rng.choice([-1, 1])
    f[rng.random(n) < 0.05] = -0.0
    s = np.array(AWKWARD, dtype=object)[rng.integers(0, len(AWKWARD), n)]
    s[rng.random(n) < 0.1] = None
    return pd.DataFrame({"x": f, "i": rng.integers(-10**12, 10**12, n), "b": rng.random(n) < 0.5,
                         "s": s, "sd": pd.array(rng.choice(["cam1", "a,b", "q\"q"], n), dtype="string"),
                         "f32": f.astype(np.float32), "u": rng.integers(0, 255, n).astype(np.uint8),
                         "col,with comma": f * 2})


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("ff,na", [("%.6f", ""), ("%.12g", ""), ("%.9g", "NA"), ("%.3e", "")])
@pytest.mark.parametrize("end", ["\n", "\r\n"])
@pytest.mark.parametrize("chunk", [7, csvtable.CHUNK_ROWS])
def test_same_bytes_as_pandas(seed, ff, na, end, chunk, monkeypatch):
    monkeypatch.setattr(csvtable, "CHUNK_ROWS", chunk)     # blocks of 7 rows: every boundary case
    rng = np.random.default_rng(seed)
    df = _frame(rng, int(rng.integers(0, 60)))
    kw = dict(index=False, lineterminator=end, float_format=ff, na_rep=na)
    want = df.to_csv(**kw)
    assert write_csv(df, **kw) == want
    b = io.BytesIO()
    write_csv(df, b, encoding="utf-8", **kw)
    assert b.getvalue() == want.encode("utf-8")
    # one column at a time (the csv module quotes a lone empty field)
    for c in df.columns:
        assert write_csv(df[[c]], **kw) == df[[c]].to_csv(**kw), c


def test_falls_back_to_pandas_where_it_does_not_format():
    df = pd.DataFrame({"o": [1.5, "x", None], "t": pd.to_datetime(["2026-01-01", "2026-01-02", None])})
    for kw in (dict(index=False, float_format="%.3f"), dict(index=True, float_format="%.3f"),
               dict(index=False), dict(index=False, float_format="%.3f", sep=";")):
        assert write_csv(df, **kw) == df.to_csv(**kw)
