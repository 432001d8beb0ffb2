"""BENCHMARKS.md's table of the JIRL issue's targets repeats figures that its subsections state. A subsection
measured again must not leave the table behind: every number of a row is one the subsection it names
states, and every number of the notes under it one the table or the subsections they quote state. The
README's table of starting points repeats rows of it, and is checked against it in turn."""

import re

from conftest import ROOT, markdown_tables, table_cells

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


def targets_table() -> tuple[dict[str, str], list[list[str]]]:
    """BENCHMARKS.md's subsections by title, and the cells of each row of its table of the issue's targets."""
    sections = subsections((ROOT / "BENCHMARKS.md").read_text())
    rows = markdown_tables(sections[TABLE].split("\n\n- ", 1)[0])[0][2]
    assert len(rows) == 20, "a row added or lost: count it here"
    return sections, rows


def test_every_figure_of_the_targets_table_is_stated_where_it_says():
    sections, rows = targets_table()
    table, notes = sections[TABLE].split("\n\n- ", 1)
    for *cells, title in rows:
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


def test_the_readmes_starting_points_are_rows_of_the_targets_table_and_parse():
    """The README's "Where to start" gives, per env, settings and what they gave: its seeds, returns and regret
    ratio are those of one row of BENCHMARKS.md's targets table, each in its column there (the ratio the
    episode form's), and its options are JIRL's."""
    from test_documented_commands import parse

    readme = (ROOT / "README.md").read_text()
    start = readme.index("| env |", readme.index("**Where to start.**"))
    table = readme[start : readme.index("\n\n", start)]
    _, target_rows = targets_table()
    rows = [table_cells(line) for line in table.splitlines()[2:]]
    assert [row[0].split(",")[0] for row in rows] == ["Pendulum-v1"] * 3 + ["LunarLanderContinuous-v3"] * 2 + ["JetRacerTrack-v0", "Walker2DBulletEnv-v0", "your own env"]
    commands = []
    for env, options, seeds, returns, ratio in rows[:-1]:
        assert any(
            f"{seeds} seeds" in setting and numbers(returns) <= numbers(target_returns) and NUMBER.findall(ratio) == NUMBER.findall(episode_form)[:1]
            for setting, episode_form, _, target_returns, *_ in target_rows
        ), f"{env}: {seeds} seeds, {returns}, {ratio} are the figures of no one row of the targets table"
        commands += [["jirl_sac_continuous.py", "--env-id", env.split(",")[0], *span.split()] for span in re.findall(r"`([^`]+)`", options)]
    assert len(commands) == 7 and parse(commands) == [None] * 7
