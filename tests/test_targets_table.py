"""BENCHMARKS.md's table of the JIRL issue's targets repeats figures that its subsections state. A subsection
measured again must not leave the table behind: every number of a row is one the subsection it names
states, and every number of the notes under it one the table or the subsections they quote state."""

import re

from conftest import ROOT

NUMBER = re.compile(r"\d[\d,]*(?:\.\d+)?")  # signs and units aside: −259.3 reads 259.3, 1,342.7 reads 1342.7
TABLE = "The issue's targets at a glance"


def subsections(text: str) -> dict[str, str]:
    """Each `### ` subsection's title -> its text, up to the next `##` or `###` heading."""
    parts = re.split(r"^(#{2,3}) (.+)$", text, flags=re.M)
    return {title: body for level, title, body in zip(parts[1::3], parts[2::3], parts[3::3]) if level == "###"}


def numbers(text: str) -> set[str]:
    return {n.replace(",", "") for n in NUMBER.findall(text)}


def test_numbers_read_as_the_table_writes_them():
    assert numbers("−259.3 / 1,342.7 at 147k–155k (1/10 on 3 of 10 seeds)") == {"259.3", "1342.7", "147", "155", "1", "10", "3"}


def test_every_figure_of_the_targets_table_is_stated_where_it_says():
    sections = subsections((ROOT / "BENCHMARKS.md").read_text())
    table, notes = sections[TABLE].split("\n\n- ", 1)
    rows = [line for line in table.splitlines() if line.startswith("| ") and not line.startswith("| setting")]
    assert len(rows) == 12, "a row added or lost: count it here"
    for row in rows:
        *cells, title = (cell.strip() for cell in row.strip("|").split("|"))
        assert title in sections, f"the row {cells[0]!r} names no subsection: {title!r}"
        missing = numbers(" ".join(cells)) - numbers(sections[title])
        assert not missing, f"the row {cells[0]!r} says {sorted(missing)}, which {title!r} does not"
    for note in ("- " + notes).split("\n- "):
        quoted = re.findall(r'"([^"]+)"', " ".join(note.split()))
        stated = numbers(table)
        for name in quoted:
            matching = [body for title, body in sections.items() if title.startswith(name)]
            assert matching, f"a note quotes {name!r}, which begins no subsection's title"
            stated |= numbers("".join(matching))
        missing = numbers(note) - stated
        assert not missing, f"the note {note[:40]!r} says {sorted(missing)}, which neither the table nor {quoted} does"
