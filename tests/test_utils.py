"""minimdm.utils: the one table formatter and the one thread helper."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from minimdm.amdm.evaluation import TABLE1_COLUMNS
from minimdm.studies.amdm_tables import read_results
from minimdm.utils import format_table, num_threads

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "amdm_tables.jsonl"


def _cells(text: str) -> list[list[str]]:
    """Split a table on runs of two or more spaces."""
    import re

    return [re.split(r" {2,}", line.strip()) for line in text.splitlines()]


def _merged(text: str) -> list[list[str]]:
    """The cells of a table printed in column groups, joined back into one row per name."""
    blocks = [_cells(block) for block in text.split("\n\n")]
    for block in blocks[1:]:
        assert [row[0] for row in block] == [row[0] for row in blocks[0]]  # the same names
    return [sum((b[i][1:] for b in blocks[1:]), blocks[0][i]) for i in range(len(blocks[0]))]


def test_format_table_cells_pairs_none_strings_and_numbers():
    rows = {
        "A-MDM": {"APD": (9.3347, 0.1579), "FS": 0.2981, "note": "ε model"},
        "MSE": {"APD": None, "FS": 123.456, "steps": 3},
    }
    text = format_table(rows)
    assert _cells(text) == [
        ["model", "APD", "FS", "note", "steps"],
        ["A-MDM", "9.33 ± 0.16", "0.30", "ε model", "-"],
        ["MSE", "-", "123.5", "-", "3"],
    ]
    lines = text.splitlines()
    assert len({len(line) for line in lines}) == 1  # fixed width
    assert lines[1].startswith("A-MDM  ") and lines[1].endswith("-")  # names left, cells right
    assert _cells(format_table(rows, ["FS"], digits=3))[1] == ["A-MDM", "0.298"]


def test_format_table_takes_a_list_of_dicts_named_by_first():
    rows = [{"method": "ddpm5", "NFE": 5, "precision": 0.42}, {"method": "aamdm", "NFE": 5}]
    assert _cells(format_table(rows, first="method")) == [
        ["method", "NFE", "precision"],
        ["ddpm5", "5", "0.42"],
        ["aamdm", "5", "-"],
    ]
    with pytest.raises(ValueError, match="at least one row"):
        format_table({})


@settings(max_examples=30, deadline=None)
@given(
    st.dictionaries(
        st.text("abcxyz", min_size=1, max_size=6),
        st.dictionaries(
            st.sampled_from(["APD", "FS", "x"]),
            st.one_of(
                st.none(),
                st.floats(-1e4, 1e4),
                st.integers(-99, 99),
                st.tuples(st.floats(0, 50), st.floats(0, 5)),
            ),
        ),
        min_size=1,
        max_size=4,
    )
)
def test_format_table_lines_are_aligned(rows):
    lines = format_table(rows).splitlines()
    assert len(lines) == len(rows) + 1
    assert len({len(line) for line in lines}) == 1


@settings(max_examples=40, deadline=None)
@given(
    n_cols=st.integers(1, 14),
    width=st.integers(20, 120),
    values=st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3),
    header=st.text("abcdefgh", min_size=1, max_size=14),
)
def test_format_table_wraps_wide_tables_into_column_groups(n_cols, width, values, header):
    """No line is wider than ``width`` (unless one column alone is), every group repeats the row
    names, and the groups read together are the one-block table."""
    columns = [f"{header}{i}" for i in range(n_cols)]
    rows = {
        "A-MDM": {c: (v, 0.5) for c, v in zip(columns, values * n_cols, strict=False)},
        "MVAE": {c: v for c, v in zip(columns, values[::-1] * n_cols, strict=False)},
    }
    text = format_table(rows, width=width)
    whole = format_table(rows, width=None)
    assert "\n\n" not in whole
    assert _merged(text) == _cells(whole)
    blocks = text.split("\n\n")
    for block in blocks:
        lines = block.splitlines()
        assert len({len(line) for line in lines}) == 1  # aligned within a group
        if len(_cells(block)[0]) > 2:  # more than one column in it: it fits
            assert len(lines[0]) <= width
    if len(whole.splitlines()[0]) <= width:
        assert text == whole  # a table that fits is printed as one block
    with pytest.raises(ValueError, match="width must be >= 1"):
        format_table(rows, width=0)


@pytest.mark.skipif(not RESULTS.exists(), reason="no stored benchmark results")
def test_chapter_4_tables_from_the_stored_rows():
    """The rows of benchmarks/results print in the order of Table 1, ``mean ± std`` per cell."""
    import json

    records = [json.loads(line) for line in RESULTS.read_text().splitlines()]
    rows = read_results(RESULTS, "table1")
    cells = _merged(format_table(rows))
    head = cells[0][1:]
    assert head == [c for c in TABLE1_COLUMNS if c in head]  # the paper's column order
    for line in cells[1:]:
        rec = [r for r in records if r["table"] == "table1" and r["model"] == line[0]][-1]  # latest
        for col, cell in zip(head, line[1:], strict=True):
            if col not in rec:
                assert cell == "-", (line[0], col)
                continue
            mean, std = (float(x) for x in cell.split(" ± "))  # 4 significant digits
            assert mean == pytest.approx(rec[col]["mean"], abs=0.051), (line[0], col)
            assert std == pytest.approx(rec[col]["std"], abs=0.0051), (line[0], col)
    with pytest.raises(ValueError, match="no rows of table 'table9'"):
        read_results(RESULTS, "table9")


def test_read_results_names_rows_by_several_fields(tmp_path):
    """Memorisation rows are told apart by model and frames; the steps sweep by T."""
    import json

    cell = {"mean": 1.5, "std": 0.25}
    lines = [
        {"table": "memorisation", "model": "A-MDM", "frames": "generated", "median": cell},
        {"table": "memorisation", "model": "A-MDM", "frames": "held-out", "median": cell},
        {"table": "steps", "T": 5, "APD": cell, "ms/frame": {"mean": 2.0, "std": 0.0}},
    ]
    path = tmp_path / "rows.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in lines))
    rows = read_results(path, "memorisation", key=("model", "frames"))
    assert list(rows) == ["A-MDM, generated", "A-MDM, held-out"]
    assert rows["A-MDM, held-out"] == {"median": (1.5, 0.25)}
    assert read_results(path, "steps", key="T") == {
        "5": {"APD": (1.5, 0.25), "ms/frame": (2.0, 0.0)}
    }


def test_num_threads_sets_and_restores_even_on_errors():
    before = torch.get_num_threads()
    with num_threads(1):
        assert torch.get_num_threads() == 1
        with num_threads(None):  # leaves the count as it is
            assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError, match="inside"):
        with num_threads(1):
            raise RuntimeError("inside")
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("n", [0, -1, 1.5, True, "2"])
def test_num_threads_rejects_a_bad_count(n):
    before = torch.get_num_threads()
    with pytest.raises(ValueError, match="n must be an integer >= 1 or None"):
        with num_threads(n):
            pass
    assert torch.get_num_threads() == before


def test_summarize_seeds_groups_and_reads(tmp_path):
    import json
    import math

    from minimdm.studies.seeds import mean_std, read_jsonl, summarize_seeds

    rows = [{"m": "a", "seed": s, "x": float(s)} for s in range(3)] + [
        {"m": "b", "seed": 0, "x": 5.0}
    ]
    p = tmp_path / "r.jsonl"
    p.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    out = summarize_seeds(read_jsonl(p), "m", ["x"])
    assert out[0] == {"m": "a", "n_seeds": 3, "x": (1.0, 1.0)}
    assert out[1]["n_seeds"] == 1 and math.isnan(out[1]["x"][1])
    assert read_jsonl(p, m="b") == rows[3:]
    with pytest.raises(ValueError, match="no lines"):
        read_jsonl(p, m="c")
    with pytest.raises(ValueError):
        mean_std([])
