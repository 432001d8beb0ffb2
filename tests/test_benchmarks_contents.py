"""BENCHMARKS.md opens with a list of its sections, linked by the anchors GitHub gives its headings; the
list must follow the headings as they are renamed, added or moved, and the sections other documents
name in quotes must exist."""

import re

from conftest import ROOT

BENCHMARKS = ROOT / "BENCHMARKS.md"


def headings(text: str) -> list[tuple[int, str]]:
    """(level, title) of each Markdown heading, in order, outside fenced code."""
    found, fenced = [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and (m := re.match(r"(#{1,6}) (.+)", line)):
            found.append((len(m.group(1)), m.group(2).strip()))
    return found


def anchor(title: str, seen: dict[str, int]) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped (`^`, backticks, `:`), each space a
    hyphen; a repeated one gets `-1`, `-2`, ... in the order of the page."""
    slug = re.sub(r"[^\w\- ]", "", title.lower()).replace(" ", "-")
    n = seen.get(slug, 0)
    seen[slug] = n + 1
    return f"{slug}-{n}" if n else slug


def contents(text: str) -> str:
    """The list of `##` and `###` sections, the second indented under the first, each linked to its anchor."""
    seen: dict[str, int] = {}
    lines = []
    for level, title in headings(text):
        link = anchor(title, seen)  # every level counts towards repeats, as on GitHub
        if level in (2, 3) and title != "Contents":
            lines.append(f"{'  ' * (level - 2)}- [{title}](#{link})")
    return "\n".join(lines)


def test_anchors_as_github_makes_them():
    seen: dict[str, int] = {}
    assert anchor("The penalty's sigma^2 = 3 on ten seeds", seen) == "the-penaltys-sigma2--3-on-ten-seeds"
    assert anchor("What `--track` costs (Weights and Biases)", seen) == "what---track-costs-weights-and-biases"
    assert anchor("SAC speed: `sac_continuous.py` vs SB3", seen) == "sac-speed-sac_continuouspy-vs-sb3"
    assert [anchor("Logs", seen) for _ in range(3)] == ["logs", "logs-1", "logs-2"]


def test_contents_nest_sections_and_count_repeats_at_every_level():
    text = "# Benchmarks\n## Contents\n## Speed\n#### Setup\n### Setup\n## Speed\n"
    assert contents(text) == "- [Speed](#speed)\n  - [Setup](#setup-1)\n- [Speed](#speed-1)"


def test_headings_skip_fenced_code():
    assert headings("# A\n```bash\n# a comment\n```\n## B\n") == [(1, "A"), (2, "B")]


def test_the_contents_list_every_section_in_order():
    text = BENCHMARKS.read_text()
    listed = text.split("\n## Contents\n\n", 1)[1].split("\n\n", 1)[0]
    expected = contents(text)
    assert listed == expected, f"BENCHMARKS.md's contents no longer follow its headings; they should read:\n\n{expected}\n"


def test_sections_named_in_quotes_exist():
    """`BENCHMARKS.md, "The floor under the 1/10 target"`: a quoted name begins a heading of BENCHMARKS.md."""
    titles = [title for _, title in headings(BENCHMARKS.read_text())]
    named = 0
    for path in [ROOT / "README.md", BENCHMARKS, *sorted((ROOT / "docs").rglob("*.md"))]:
        for name in re.findall(r'BENCHMARKS(?:\.md)?(?:\'s|,) "([^"]+)"', " ".join(path.read_text().split())):
            named += 1
            assert any(title.startswith(name) for title in titles), f"{path.name} names {name!r}, which begins no heading of BENCHMARKS.md"
    assert named >= 5, "the README no longer names sections of BENCHMARKS.md this way: check the pattern"
