"""BENCHMARKS.md's summaries are arithmetic on figures it also prints: a median in parentheses after the
figures it summarises, a table's median and mean ± 95 % CI rows under its seed rows, each seed's SAC / JIRL
regret ratio, and the targets table's ratios of medians, counts of seeds and shares of SAC's return. A
seed measured again, or a summary typed by hand, must not leave them behind, so each is computed here
again from the printed figures. Those are rounded: a median or a mean may differ from the computation by
one unit of its last digit, a confidence interval by that or 1 % of itself, and a ratio or a share by half
a unit plus what the rounding of the figures it divides allows."""

import itertools
import re
import statistics
from typing import NamedTuple

from scipy import stats

from conftest import ROOT, figure_value, markdown_tables
from test_targets_table import targets_table

FIGURE = r"[−-]?\d[\d,]*(?:\.\d+)?"
FIGURES = rf"{FIGURE}(?: ?%)?(?: / {FIGURE}(?: ?%)?)+"  # 1,431 / 2,443 / 1,853, or 89.9 / 93.4 %
MEDIAN_AFTER = re.compile(rf"({FIGURES}) \(({FIGURE})(?: ?%)?\)")
SEED = re.compile(r"\d+")
MEAN_CI = "mean ± 95 % CI"
ONE_TENTH = re.compile(r"1/10 on (every seed|no seed|(\d+) of (\d+) seeds)")


def unit(figure: str) -> float:
    """One unit of a figure's last digit: 0.1 for −203.1, 1 for 2,567."""
    return 10.0 ** -len(figure.partition(".")[2])


def figures(text: str) -> list[str]:
    return re.findall(FIGURE, text)


def is_ratio(stated: str, sac: str, jirl: str) -> bool:
    """A printed ratio is SAC's printed regret over JIRL's, within half a unit of its last digit and what the
    rounding of the two regrets allows."""
    quotient = figure_value(sac) / figure_value(jirl)
    slack = quotient * (0.5 * unit(sac) / figure_value(sac) + 0.5 * unit(jirl) / (figure_value(jirl) - 0.5 * unit(jirl)))
    return abs(quotient - figure_value(stated)) <= 0.5 * unit(stated) + slack + 1e-9


def tables() -> list[tuple[int, list[str], list[list[str]]]]:
    return markdown_tables((ROOT / "BENCHMARKS.md").read_text())


def test_the_helpers_read_figures_as_printed():
    assert figures("−259.3 / 1,342.7 (5 %)") == ["−259.3", "1,342.7", "5"]
    assert [figure_value("−1,342.7"), unit("−1,342.7"), unit("2,567")] == [-1342.7, 0.1, 1.0]
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
                if summary is None or "median" not in f"{name} {row[0]}":
                    continue
                listed, stated = summary.groups()
                median = statistics.median(figure_value(f) for f in figures(listed))
                assert abs(median - figure_value(stated)) <= unit(stated) + 1e-9, f"table at line {line}, {row[0]!r}, {name!r}: {cell} has median {median:g}"
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
                        median = statistics.median(figure_value(part[i]) for part in parts)
                        assert abs(median - figure_value(figure)) <= unit(figure) + 1e-9, f"{where}: {cell}, but the median is {median:g}"
                else:
                    mean, half = figures(cell)
                    column_values = [figure_value(part[0]) for part in parts]
                    computed_half = stats.t.ppf(0.975, len(seeds) - 1) * statistics.stdev(column_values) / len(seeds) ** 0.5
                    assert abs(statistics.fmean(column_values) - figure_value(mean)) <= unit(mean) + 1e-9, f"{where}: {cell}, but the mean is {statistics.fmean(column_values):g}"
                    assert abs(computed_half - figure_value(half)) <= max(unit(half), 0.01 * computed_half) + 1e-9, f"{where}: {cell}, but the half-width is {computed_half:g}"
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
                assert is_ratio(stated, sac, jirl), f"table at line {line}, seed {row[0]}, {form}: {stated}, but {sac} / {jirl} is {figure_value(sac) / figure_value(jirl):.2f}"
                checked += 1
    assert checked >= 140, "fewer ratios than BENCHMARKS.md states: are its tables' headers still read?"


# Rows of the targets table whose subsection gives JIRL's seeds only, and the subsection with SAC's runs
SAC_ELSEWHERE = {
    "Lunar Lander 100k, `--penalty-sigma2 3`, 10 seeds (Xeon)": "The earned hand-over on ten seeds, on another CPU (LunarLanderContinuous-v3, 100k steps)",
}


class Regrets(NamedTuple):
    """One setting's regret as a table prints it, per step and in the episode form: its medians, and each
    seed's where the table gives them."""

    medians: tuple[str, str]
    seeds: list[tuple[str, str]] | None


def stated_regrets(text: str) -> dict[str, list[Regrets]]:
    """The regrets that the tables in `text` give, {"SAC": [...], "JIRL": [...]}. A table of seeds gives them
    under `SAC regret per step` and `JIRL ... regret (episode form)`, the medians in its median row; a table
    of methods in a row per method, as `a / b / c (median)` or `median (mean ± CI)`."""
    found: dict[str, list[Regrets]] = {"SAC": [], "JIRL": []}
    for _, header, rows in markdown_tables(text):
        medians = [row for row in rows if row[0] == "median"]
        seeds = [row for row in rows if SEED.fullmatch(row[0])]
        for method in found:
            columns = [i for form in ("regret per step", "regret (episode form)") for i, name in enumerate(header) if name.startswith(method) and name.endswith(form)]
            if medians and len(columns) == 2:
                found[method].append(Regrets((medians[0][columns[0]], medians[0][columns[1]]), [(seed[columns[0]], seed[columns[1]]) for seed in seeds]))
        step = [i for i, name in enumerate(header) if "regret per step" in name]
        episode = [i for i, name in enumerate(header) if "episode form" in name or "regret per episode" in name]
        if not (step and episode) or medians:
            continue
        for row in rows:
            cells = (row[step[0]], row[episode[0]])
            listed = [MEDIAN_AFTER.fullmatch(cell) for cell in cells]
            alone = [re.fullmatch(rf"({FIGURE}) \({FIGURE} ± {FIGURE}\)", cell) for cell in cells]
            method = "SAC" if row[0].startswith("SAC") else "JIRL"
            if listed[0] and listed[1]:
                by_seed = list(zip(figures(listed[0].group(1)), figures(listed[1].group(1)), strict=True))
                found[method].append(Regrets((listed[0].group(2), listed[1].group(2)), by_seed))
            elif alone[0] and alone[1]:
                found[method].append(Regrets((alone[0].group(1), alone[1].group(1)), None))
    return found


def cited_regrets(sections: dict[str, str], setting: str, title: str) -> list[tuple[Regrets, Regrets]]:
    """Each pair of SAC's regrets and one JIRL setting's that the subsection a targets row names gives."""
    regrets = stated_regrets(sections[title])
    if setting in SAC_ELSEWHERE:
        regrets["SAC"] = stated_regrets(sections[SAC_ELSEWHERE[setting]])["SAC"]
    return list(itertools.product(regrets["SAC"], regrets["JIRL"]))


def test_the_targets_tables_regret_ratios_are_sacs_median_over_jirls():
    """Each row's two ratios, SAC / JIRL per step and in the episode form, are those of SAC's medians and one
    JIRL setting's, in the subsection the row names."""
    sections, targets = targets_table()
    for setting, episode_form, per_step, *_, title in targets:
        stated = [figures(per_step)[0], figures(episode_form)[0]]
        pairs = cited_regrets(sections, setting, title)
        given = [" and ".join(f"{figure_value(s) / figure_value(j):.2f}" for s, j in zip(sac.medians, jirl.medians)) for sac, jirl in pairs]
        assert any(all(map(is_ratio, stated, sac.medians, jirl.medians)) for sac, jirl in pairs), f"{setting!r}: {stated[0]}× per step and {stated[1]}× in the episode form, but {title!r} gives {given}"


def test_the_targets_tables_seeds_at_one_tenth_are_counted_from_the_seeds():
    """`(1/10 on 3 of 10 seeds)`, `on every seed`, `on no seed`: the seeds whose SAC / JIRL regret is 10 or more,
    in the form of the cell, counted from the regrets seed by seed of the setting whose medians give the row's
    ratios."""
    sections, targets = targets_table()
    checked = 0
    for setting, episode_form, per_step, *_, title in targets:
        stated = [figures(per_step)[0], figures(episode_form)[0]]
        claims = [ONE_TENTH.search(cell) for cell in (per_step, episode_form)]
        if not any(claims):
            continue
        pairs = [(sac, jirl) for sac, jirl in cited_regrets(sections, setting, title) if all(map(is_ratio, stated, sac.medians, jirl.medians)) and sac.seeds and jirl.seeds]
        assert pairs, f"{setting!r} counts seeds at 1/10, but {title!r} gives its regrets seed by seed nowhere"
        sac, jirl = pairs[0]
        for form, claim in enumerate(claims):
            if claim is None:
                continue
            ratios = [figure_value(s[form]) / figure_value(j[form]) for s, j in zip(sac.seeds, jirl.seeds, strict=True)]
            if claim.group(2) is None:
                count = len(ratios) if claim.group(1) == "every seed" else 0
            else:
                count = int(claim.group(2))
            assert claim.group(3) in (None, str(len(ratios))), f"{setting!r}: {claim.group()}, but {title!r} gives {len(ratios)} seeds"
            assert sum(ratio >= 10 for ratio in ratios) == count, f"{setting!r}: {claim.group()}, but the seeds' ratios are {[round(r, 2) for r in ratios]}"
            checked += 1
    assert checked >= 14, "fewer counts than the targets table gives: is the cell still read?"


def test_the_targets_tables_return_percentages_are_jirls_median_against_sacs():
    """Each percentage in a row's final-return cell, `JIRL / SAC / baseline: ...`, is JIRL's median as a share of
    SAC's (`118 % of SAC's`) or, where returns are negative, JIRL's shortfall from SAC's as a share of it
    (`8.0 % short`, `within 3.6 %`). The target's own 5 % is the one other percentage; 5 % below SAC's is
    the figure that follows it."""
    _, targets = targets_table()
    checked = 0
    for setting, _, _, returns, *_ in targets:
        jirl, sac = figures(returns)[:2]
        j, s, uj, us = figure_value(jirl), figure_value(sac), 0.5 * unit(jirl), 0.5 * unit(sac)  # u: half a unit, the rounding
        if s > 0:
            share = 100 * j / s
            slack = share * (uj / abs(j) + us / s)
        else:
            share = 100 * abs(j - s) / abs(s)
            slack = 100 * (uj + us) / abs(s) + share * us / abs(s)
        for percent in re.findall(rf"({FIGURE}) %", returns):
            if figure_value(percent) == 5:
                continue
            assert abs(share - figure_value(percent)) <= 0.5 * unit(percent) + slack + 1e-9, f"{setting!r}: {percent} % in {returns!r}, but {jirl} against {sac} is {share:.2f} %"
            checked += 1
        for threshold in re.findall(rf"5 % below SAC's is ({FIGURE})", returns):
            assert abs(s - 0.05 * abs(s) - figure_value(threshold)) <= 0.5 * unit(threshold) + 1.05 * us + 1e-9, f"{setting!r}: 5 % below {sac} is not {threshold}"
            checked += 1
    assert checked >= 13, "fewer percentages than the targets table gives: is the cell still read?"


def test_the_targets_tables_seeds_above_the_baseline_and_within_5_percent_are_counted_from_the_seeds():
    """`9 of 10 above the baseline` and `6 of 10 seeds within 5 %` in a row's final-return cell, counted from
    the seed table whose median row gives the row's JIRL return, where its subsection has one: seeds whose
    JIRL return is above their baseline's, and seeds whose JIRL return is at least their SAC's less 5 % of
    it."""
    sections, targets = targets_table()
    checked = 0
    for setting, _, _, returns, *_, title in targets:
        claims = re.findall(r"(\d+) of (\d+) (?:seeds )?(above the baseline|above it|within 5 %)", returns)
        if not claims:
            continue
        seed_tables = []
        for _, header, rows in markdown_tables(sections[title]):
            columns = {name.split()[0]: i for i, name in enumerate(header) if name.endswith("eval return") or name == "baseline return"}
            medians = [row for row in rows if row[0] == "median"]
            if "JIRL" in columns and medians and medians[0][columns["JIRL"]] == figures(returns)[0]:
                seed_tables.append((columns, [row for row in rows if SEED.fullmatch(row[0])]))
        if not seed_tables:
            continue
        columns, seeds = seed_tables[0]
        for count, of, what in claims:
            if what == "within 5 %":
                meeting = [figure_value(seed[columns["JIRL"]]) >= figure_value(seed[columns["SAC"]]) - 0.05 * abs(figure_value(seed[columns["SAC"]])) for seed in seeds]
            else:
                meeting = [figure_value(seed[columns["JIRL"]]) > figure_value(seed[columns["baseline"]]) for seed in seeds]
            assert (int(count), int(of)) == (sum(meeting), len(seeds)), f"{setting!r}: {count} of {of} {what}, but the seeds give {sum(meeting)} of {len(seeds)}"
            checked += 1
    assert checked >= 10, "fewer counts than the targets table gives: is the cell still read?"
