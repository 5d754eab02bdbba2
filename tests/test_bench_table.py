"""`make bench` writes the table of docs/benchmarks.md (issue 18 item 4): benchmarks/table.py replaces the lines
between the document's two marker lines and nothing else, and refuses a document without them before it runs."""

import os
import sys

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
import table  # noqa: E402

DOC = f"# Benchmarks\n\nIntro.\n\n{table.DOCS_START}\nold table\nold line\n{table.DOCS_END}\n\nLater runs.\n"


def test_the_table_between_the_markers_is_replaced_and_the_rest_kept_byte_for_byte():
    out = table.spliced(DOC, "Machine: x.\n\n| case |\n|---|\n", "doc.md")
    assert out == f"# Benchmarks\n\nIntro.\n\n{table.DOCS_START}\nMachine: x.\n\n| case |\n|---|\n{table.DOCS_END}\n\nLater runs.\n"
    assert table.spliced(out, "old table\nold line", "doc.md") == DOC  # the same splice the other way round


@pytest.mark.parametrize("doc, found", [
    ("no markers\n", "found 0 and 0"),
    (f"{table.DOCS_START}\nonly a start\n", "found 1 and 0"),
    (f"{table.DOCS_END}\nthe end first\n{table.DOCS_START}\n", "found 1 and 1"),
    (f"{table.DOCS_START}\n{table.DOCS_START}\n{table.DOCS_END}\n", "found 2 and 1"),
])
def test_a_document_without_one_ordered_pair_of_markers_is_named_and_refused(doc, found):
    with pytest.raises(ValueError, match=f"docs/x.md: needs one line .* \\({found}\\)"):
        table.spliced(doc, "table", "docs/x.md")


def test_the_repository_document_has_its_markers_and_the_run_checks_them_first(tmp_path):
    with open(table.DOCS, encoding="utf-8") as f:
        doc = f.read()
    assert table.spliced(doc, "", table.DOCS).count(table.DOCS_START) == 1
    bad = tmp_path / "benchmarks.md"
    bad.write_text("no markers\n")
    with pytest.raises(ValueError, match="benchmarks.md: needs one line"):  # before any part runs (those take minutes)
        table.main(["--docs", str(bad), "--out", str(tmp_path / "bench.md")])
    assert not (tmp_path / "bench.md").exists() and bad.read_text() == "no markers\n"


def test_a_run_of_every_part_writes_both_files_and_a_subset_leaves_the_docs(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(table, "PARTS", {"fk": lambda max_n: ["| FK row |"], "own": lambda: ["| own row |"]})
    doc, out = tmp_path / "benchmarks.md", tmp_path / "bench.md"
    doc.write_text(DOC)
    table.main(["--docs", str(doc), "--out", str(out)])
    text = out.read_text()
    assert text.startswith("Machine: ") and "| FK row |\n| own row |\n" in text
    assert doc.read_text() == table.spliced(DOC, text, "doc") and "Later runs." in doc.read_text()
    written = doc.read_text()
    table.main(["--docs", str(doc), "--out", str(out), "--parts", "own"])
    assert doc.read_text() == written and "| FK row |" not in out.read_text()
    assert "left as it is: --parts ran a subset" in capsys.readouterr().out
