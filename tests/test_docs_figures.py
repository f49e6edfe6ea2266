"""The docs' figure script reads the committed benchmark tables and draws from them."""

import pathlib

from experiments.paper import figures

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_markdown_tables_are_read_under_their_headings():
    text = (
        "# A\n\n| x | y |\n|---|---|\n| 1 | 2 |\n| 3 | 4 |\n\ntext\n\n## B\n| z |\n|---|\n| 5 |\n"
    )
    assert figures.markdown_tables(text) == {
        "A": [{"x": "1", "y": "2"}, {"x": "3", "y": "4"}],
        "B": [{"z": "5"}],
    }


def test_speed_accuracy_figure_from_benchmarks_md(tmp_path):
    filters, runs = figures.accuracy_rows(ROOT / "BENCHMARKS.md")
    # F = 1..6 x separable/full x float32/bfloat16 filter rows; Adam + 24 texture runs.
    assert len(filters) == 24 and len(runs) == 25
    assert {r["mode"] for r in runs} == {"-", "separable", "full"}
    path = figures.speed_accuracy(tmp_path, ROOT / "BENCHMARKS.md")
    assert path.stat().st_size > 10_000
