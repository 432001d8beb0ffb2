"""BENCHMARKS.md's summaries are arithmetic on figures it also prints: a median in parentheses after the
figures it summarises, a table's median and mean ± 95 % CI rows under its seed rows, and each seed's
SAC / JIRL regret ratio. A seed measured again, or a summary typed by hand, must not leave them behind,
so each is computed here again from the printed figures. Those are rounded: a median or a mean may differ
from the computation by one unit of its last digit, a confidence interval by that or 1 % of itself, and a
ratio by half a unit plus what the rounding of its two regrets allows."""

import re
import statistics

from scipy import stats

from conftest import ROOT, table_cells

FIGURE = r"[−-]?\d[\d,]*(?:\.\d+)?"
FIGURES = rf"{FIGURE}(?: ?%)?(?: / {FIGURE}(?: ?%)?)+"  # 1,431 / 2,443 / 1,853, or 89.9 / 93.4 %
MEDIAN_AFTER = re.compile(rf"({FIGURES}) \(({FIGURE})(?: ?%)?\)")
SEED = re.compile(r"\d+")
MEAN_CI = "mean ± 95 % CI"


def value(figure: str) -> float:
    return float(figure.replace(",", "").replace("−", "-"))


def unit(figure: str) -> float:
    """One unit of a figure's last digit: 0.1 for −203.1, 1 for 2,567."""
    return 10.0 ** -len(figure.partition(".")[2])


def figures(text: str) -> list[str]:
    return re.findall(FIGURE, text)


def tables() -> list[tuple[int, list[str], list[list[str]]]]:
    """Each table of BENCHMARKS.md: the line of its header, the header's cells, and its rows' cells, bold
    marks dropped."""
    found, lines = [], (ROOT / "BENCHMARKS.md").read_text().replace("**", "").splitlines()
    start = None
    for number, line in enumerate([*lines, ""], 1):
        if line.startswith("|") and start is None:
            start = number
        elif not line.startswith("|") and start is not None:
            header, _, *rows = lines[start - 1 : number - 1]
            found.append((start, table_cells(header), [table_cells(row) for row in rows]))
            start = None
    return found


def test_the_helpers_read_figures_as_printed():
    assert figures("−259.3 / 1,342.7 (5 %)") == ["−259.3", "1,342.7", "5"]
    assert [value("−1,342.7"), unit("−1,342.7"), unit("2,567")] == [-1342.7, 0.1, 1.0]
    assert MEDIAN_AFTER.fullmatch("89.9 / 93.4 % (91.6 %)").groups() == ("89.9 / 93.4 %", "91.6")
    assert MEDIAN_AFTER.fullmatch("2.6× / 4.6× (3.3×)") is None  # a ratio of medians (that table says so)


def test_a_median_in_parentheses_is_the_median_of_the_figures_before_it():
    """In a cell such as `−210.2 / −259.3 / −260.4 (−259.3)`, where its column's header or its row says
    median."""
    checked = 0
    for line, header, rows in tables():
        for row in rows:
            for name, cell in zip(header[1:], row[1:]):
                summary = MEDIAN_AFTER.fullmatch(cell)
                if summary is None or "median" not in name + row[0]:
                    continue
                listed, stated = summary.groups()
                median = statistics.median(value(f) for f in figures(listed))
                assert abs(median - value(stated)) <= unit(stated) + 1e-9, f"table at line {line}, {row[0]!r}, {name!r}: {cell} has median {median:g}"
                checked += 1
    assert checked >= 101, "fewer medians than BENCHMARKS.md states: is the pattern still read?"


def test_median_and_mean_rows_summarise_the_seed_rows():
    """A table whose rows are seeds ends with a row of each column's median and one of its mean ± the
    half-width of its 95 % confidence interval (Student's t, as `benchmarks/learning.py` prints it). A cell
    of two figures, `5.4 / 9.2`, holds the medians of its column's two."""
    checked = 0
    for line, header, rows in tables():
        seeds = [row for row in rows if SEED.fullmatch(row[0])]
        for row in rows:
            if len(seeds) < 3 or row[0] not in ("median", MEAN_CI):
                continue
            for column, (name, cell) in enumerate(zip(header, row)):
                if column == 0 or not cell:
                    continue
                where = f"table at line {line}, {row[0]!r}, {name!r}"
                parts = [figures(seed[column]) for seed in seeds]
                if row[0] == "median":
                    stated = figures(cell)
                    assert all(len(part) == len(stated) for part in parts), f"{where}: {cell} does not summarise {[s[column] for s in seeds]}"
                    for i, figure in enumerate(stated):
                        median = statistics.median(value(part[i]) for part in parts)
                        assert abs(median - value(figure)) <= unit(figure) + 1e-9, f"{where}: {cell}, but the median is {median:g}"
                else:
                    mean, half = figures(cell)
                    column_values = [value(part[0]) for part in parts]
                    computed_half = stats.t.ppf(0.975, len(seeds) - 1) * statistics.stdev(column_values) / len(seeds) ** 0.5
                    assert abs(statistics.fmean(column_values) - value(mean)) <= unit(mean) + 1e-9, f"{where}: {cell}, but the mean is {statistics.fmean(column_values):g}"
                    assert abs(computed_half - value(half)) <= max(unit(half), 0.01 * computed_half) + 1e-9, f"{where}: {cell}, but the half-width is {computed_half:g}"
                checked += 1
    assert checked >= 149, "fewer summaries than BENCHMARKS.md states: is its seed tables' shape still read?"


def test_each_seeds_ratio_is_sacs_regret_over_jirls():
    """`SAC / JIRL regret, per step / episode form` on a seed's row, where the table gives both regrets."""
    checked = 0
    for line, header, rows in tables():
        ratio = [i for i, name in enumerate(header) if name.startswith("SAC / JIRL regret")]
        regrets = {
            (method, form): i
            for i, name in enumerate(header)
            for method in ("SAC", "JIRL")
            for form in ("regret per step", "regret (episode form)")
            if name.startswith(method) and name.endswith(form)
        }
        if not ratio or len(regrets) < 4:
            continue
        for row in rows:
            if not SEED.fullmatch(row[0]):
                continue
            for form, stated in zip(("regret per step", "regret (episode form)"), figures(row[ratio[0]]), strict=True):
                sac, jirl = row[regrets["SAC", form]], row[regrets["JIRL", form]]
                quotient = value(sac) / value(jirl)
                slack = quotient * (0.5 * unit(sac) / value(sac) + 0.5 * unit(jirl) / (value(jirl) - 0.5 * unit(jirl)))
                assert abs(quotient - value(stated)) <= 0.5 * unit(stated) + slack + 1e-9, f"table at line {line}, seed {row[0]}, {form}: {stated}, but {sac} / {jirl} is {quotient:.2f}"
                checked += 1
    assert checked >= 140, "fewer ratios than BENCHMARKS.md states: are its tables' headers still read?"
