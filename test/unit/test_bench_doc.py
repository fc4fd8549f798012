"""bench/run.py writes docs/benchmarks.md: a rerun replaces a section's generated text and keeps what
was written into it by hand between ``<!-- kept -->`` and ``<!-- /kept -->``."""
from __future__ import annotations

import importlib.util

from helpers import REPO

_spec = importlib.util.spec_from_file_location("bench_run", REPO / "bench" / "run.py")
bench_run = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_run)

OLD_DOC = """# Benchmarks

- Date: then

## Alpha

old figure 1.0

<!-- kept -->
**Re-measured** on a branch: 0.9
<!-- /kept -->

| a | b |
|---|---|
| 1 | 2 |

<!-- kept -->
Second note.
<!-- /kept -->

_(ran in 3 s)_

## Beta

beta text

<!-- kept -->
beta note
<!-- /kept -->
"""


def _write(tmp_path, text: str):
    path = tmp_path / "benchmarks.md"
    path.write_text(text, encoding="utf-8")
    return str(path)


def test_a_rerun_replaces_the_figures_and_keeps_the_notes_in_order(tmp_path):
    new = "## Alpha\n\nnew figure 2.0\n\n| a | b |\n|---|---|\n| 3 | 4 |\n\n_(ran in 5 s)_\n"
    text = bench_run.merge_doc(_write(tmp_path, OLD_DOC), [new], ["- Date: now"], ["alpha"])
    alpha = text[text.index("## Alpha"):text.index("## Beta")]
    assert "old figure" not in alpha and "| 1 | 2 |" not in alpha
    assert "new figure 2.0" in alpha and "| 3 | 4 |" in alpha
    first, second = alpha.index("**Re-measured** on a branch: 0.9"), alpha.index("Second note.")
    assert alpha.index("| 3 | 4 |") < first < second < alpha.index("_(ran in 5 s)_")
    assert alpha.count("<!-- kept -->") == 2 and alpha.count("<!-- /kept -->") == 2
    assert "_(ran in 3 s)_" not in alpha
    # The section not run is untouched, its note too; the header says what was rerun.
    assert "beta text" in text and "beta note" in text
    assert "- Rerun with --only alpha: Date: now" in text


def test_a_note_already_in_the_new_section_is_not_doubled(tmp_path):
    note = "<!-- kept -->\nSecond note.\n<!-- /kept -->"
    new = f"## Alpha\n\nnew figure 2.0\n\n{note}\n\n_(ran in 5 s)_\n"
    text = bench_run.merge_doc(_write(tmp_path, OLD_DOC), [new], ["- Date: now"], ["alpha"])
    assert text.count("Second note.") == 1 and text.count("0.9") == 1


def test_a_section_without_notes_or_a_run_line_is_taken_as_rendered():
    new = "## Gamma\n\nfigures\n"
    assert bench_run.with_kept(new, "## Gamma\n\nold figures\n") == new
    out = bench_run.with_kept(new, "## Gamma\n\nold\n\n<!-- kept -->\nopen note, never closed\n")
    assert out.endswith("figures\n\n<!-- kept -->\nopen note, never closed\n")
