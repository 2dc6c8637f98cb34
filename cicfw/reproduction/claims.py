"""The paper's claims as tested parts (data: ``claims:`` in conf/reproduce.yaml) and their verdicts:
each part's difference over seeds (within one CPU kind where it can be), its two-sided p-value against the
part's null (0, or the equivalence margin for "not better than"), Holm's over the family, the paper's own
figure."""
from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from importlib.resources import files
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import yaml

from cicfw.core.errors import CicfwError, ConfigError
from cicfw.reproduction.analysis import Analysis, Pairing, boot_value, percentile_interval
from cicfw.reproduction.cells import SELECTOR_NAMES, SELECTORS, CellResult, episode_terms
from cicfw.reproduction.seed_stats import (TOO_FEW, Estimate, difference, family_level, holm, ratio_interval,
                                          with_episode_floor, with_ratio_floor, word, word_record)

SUPPORTED, CONTRADICTED, INCONCLUSIVE, NOT_RUN = "supported", "contradicted", "inconclusive", "not run"
NOT_SHOWN = "not shown"
#: greater / less: A beats B / A below B; not_greater / not_less: "A failed to improve on B" / "A is no worse
#: than B", tested against the equivalence margin (``equivalence_margin`` in conf/reproduce.yaml)
TESTS = ("greater", "less", "not_greater", "not_less")
MARGIN_TESTS = ("not_greater", "not_less")


#: the family of a claim that names none: the paper's main comparison (Tables 1 and 4)
MAIN_FAMILY = "main"


def holm_families(claims: Sequence[Mapping[str, Any]]) -> dict[str, int]:
    """Holm's families, fixed in advance, and their sizes: every part of every claim of a family, whether
    it could be tested or not (``claims``: the judged claims, ``judge``'s output, each with its ``parts``
    and ``family``), in the order the families first appear."""
    sizes: dict[str, int] = {}
    for c in claims:
        fam = c.get("family", MAIN_FAMILY)
        sizes[fam] = sizes.get(fam, 0) + len(c["parts"])
    return sizes


@dataclass(frozen=True)
class Part:
    """One tested part of a claim: A - b_scale x B on ``on`` (a selector), or, with ``on="gap"``, A's
    advantage over B on ``hard`` minus that on ``easy``; ``test`` says which way the claim goes
    (``TESTS``); ``relative`` also reports A / B - 1. ``on`` is the part's
    ``column:`` in conf/reproduce.yaml; ``b_scale`` multiplies B before the difference is taken (the
    statistics see B already scaled; the episodes' floor scales B's terms, ``part_terms``)."""

    a: str
    b: str
    on: str = "overall"
    test: str = "greater"
    relative: bool = False
    hard: str | None = None
    easy: str | None = None
    b_scale: float = 1.0

    def text(self, labels: Mapping[str, str], margin: float | None = None) -> str:
        """The part as the report words it, rows by their labels: "GTU > CIL (new town / new weathers)";
        a margin test names its ``margin``: "Classification not better than CIL by 5 points or more"."""
        la, lb = labels.get(self.a, self.a), labels.get(self.b, self.b)
        lb = lb if self.b_scale == 1.0 else f"{self.b_scale:g} x {lb}"
        by = f" by {margin:g} points or more" if self.test in MARGIN_TESTS and margin is not None else ""
        if self.on == "gap":
            how = {"greater": "larger", "less": "smaller", "not_greater": "not larger", "not_less": "not smaller"}
            return (f"{la} − {lb} {how[self.test]} in {SELECTOR_NAMES[self.hard]} than in "
                    f"{SELECTOR_NAMES[self.easy]}{by}")
        op = {"greater": ">", "less": "<", "not_greater": "not better than", "not_less": "not worse than"}[self.test]
        return f"{la} {op} {lb}{by} ({SELECTOR_NAMES[self.on]})"

    def null(self, margin: float) -> float:
        """The value of A - B the part's two-sided test is against: 0 for a direction, +margin for "not better
        than" (supported below it), -margin for "not worse than" (supported above it)."""
        return {"not_greater": margin, "not_less": -margin}.get(self.test, 0.0)

    def values(self, cells: Mapping[str, Sequence[CellResult]], row: str) -> dict[int, float]:
        """seed -> the statistic this part compares, of ``row``'s ``cells`` (each row's cells the comparison
        uses): its success on a selector (``cells.SELECTORS``), or a gap's difference of two."""
        per_seed = lambda on: {c.seed: c.value(on) for c in cells[row]}  # noqa: E731
        if self.on == "gap":
            hard, easy = per_seed(self.hard), per_seed(self.easy)
            return {s: hard[s] - easy[s] for s in hard}
        return per_seed(self.on)

    def paper(self, paper: Mapping[str, Sequence[float]]) -> float | None:
        """The paper's value of this difference (from its Table 4), None when a row has no paper values."""
        if not paper.get(self.a) or not paper.get(self.b):
            return None
        val = lambda row, on: float(np.mean([paper[row][i] for i in SELECTORS[on]]))  # noqa: E731
        if self.on == "gap":
            return ((val(self.a, self.hard) - self.b_scale * val(self.b, self.hard))
                    - (val(self.a, self.easy) - self.b_scale * val(self.b, self.easy)))
        return val(self.a, self.on) - self.b_scale * val(self.b, self.on)

    def paper_relative(self, paper: Mapping[str, Sequence[float]]) -> float | None:
        """The paper's A / B - 1 for a ``relative`` part (None for a gap or without the paper's values)."""
        if not self.relative or not paper.get(self.a) or not paper.get(self.b) or self.on == "gap":
            return None
        va, vb = (float(np.mean([paper[r][i] for i in SELECTORS[self.on]])) for r in (self.a, self.b))
        return va / vb - 1.0 if vb else None


@dataclass(frozen=True)
class Claim:
    """One sentence of the paper (``quote``, from ``source``) as tested parts; a claim's verdict combines
    its parts' (``combine``)."""

    id: str
    text: str
    parts: tuple[Part, ...]
    quote: str = ""
    source: str = ""
    family: str = MAIN_FAMILY  # Holm adjusts within a family: a separate question (Tables 2 and 3) is its own


def claim_part(a: str, b: str, column: str = "overall", test: str = "greater", relative: bool = False,
               hard: Optional[str] = None, easy: Optional[str] = None, b_scale: float = 1.0) -> Part:
    """A part as ``claims:`` in conf/reproduce.yaml writes it (these arguments are its keys: the reproduce
    config's schema takes them from here), its column(s) and test checked: a ValueError naming what is accepted."""
    for s in ([hard, easy] if column == "gap" else [column]):
        if s not in SELECTORS:
            raise CicfwError(f"unknown column {s!r}; accepted: {', '.join(SELECTORS)}"
                             + (" (a gap needs hard and easy)" if column == "gap" else ", gap"))
    if test not in TESTS:
        raise CicfwError(f"unknown test {test!r}; accepted: {', '.join(TESTS)}")
    return Part(a=str(a), b=str(b), on=column, test=test, relative=bool(relative), hard=hard, easy=easy,
                b_scale=float(b_scale))


def claim_entry(id: str, claim: str, parts: Sequence[Mapping[str, Any]], quote: str = "", source: str = "",
                family: str = MAIN_FAMILY) -> Claim:
    """A claim as ``claims:`` in conf/reproduce.yaml writes it (these arguments are its keys), each part
    through ``claim_part``."""
    out = []
    for j, p in enumerate(parts):
        unknown = sorted({str(k) for k in p} - set(PART_KEYS))
        if unknown or "a" not in p or "b" not in p:
            raise CicfwError(f"part {j}: needs a and b; accepted keys: {', '.join(PART_KEYS)}"
                             + (f" (unknown: {', '.join(unknown)})" if unknown else ""))
        try:
            out.append(claim_part(**p))
        except ValueError as err:
            raise CicfwError(f"part {j}: {err}") from None
    return Claim(id=str(id), text=str(claim), parts=tuple(out), quote=str(quote or ""), source=str(source or ""),
                 family=str(family or MAIN_FAMILY))


#: the keys of a claim and of its part: ``claim_entry``'s and ``claim_part``'s arguments
CLAIM_KEYS = tuple(inspect.signature(claim_entry).parameters)
PART_KEYS = tuple(inspect.signature(claim_part).parameters)


def load_claims(spec: Sequence[Mapping[str, Any]]) -> list[Claim]:
    """Claims from their data (``claims:`` in conf/reproduce.yaml), checked: one clear error per bad entry."""
    out = []
    for k, c in enumerate(spec or []):
        where = f"claims[{k}] ({c.get('id', '?')})"
        for key in ("id", "claim", "parts"):
            if not c.get(key):
                raise CicfwError(f"{where} has no {key!r}; a claim needs id, claim, quote, source and parts")
        unknown = sorted({str(key) for key in c} - set(CLAIM_KEYS))
        if unknown:
            raise CicfwError(f"{where}: unknown key {unknown[0]!r}; accepted: {', '.join(CLAIM_KEYS)}")
        try:
            out.append(claim_entry(**c))
        except ValueError as err:
            raise CicfwError(f"{where} {err}") from None
    return out


def default_claims() -> list[Claim]:
    """The paper's claims as shipped in ``conf/reproduce.yaml`` (``claims:``), read as plain YAML (no Hydra
    state is touched, so this works inside a running app too)."""
    return load_claims(shipped_config()["claims"])


def default_margin() -> float:
    """The equivalence margin shipped in ``conf/reproduce.yaml`` (``equivalence_margin``, points), checked."""
    return check_margin(shipped_config().get("equivalence_margin"))


def shipped_config() -> dict[str, Any]:
    """conf/reproduce.yaml as shipped, read as plain YAML (its claims, margin and fine tuning's candidates
    hold no interpolation, so these are the composed values) without touching Hydra's state."""
    return yaml.safe_load(files("cicfw.conf").joinpath("reproduce.yaml").read_text())


def check_margin(value: Any) -> float:
    """``equivalence_margin`` as a number of points, or one error line saying what it takes."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    if not ok:
        raise ConfigError("equivalence_margin", value, "a positive number of points", message=(
            f"equivalence_margin={value!r}: give a positive number of points of success (e.g. 5), the margin a "
            f"'not better than' claim is tested against"))
    return float(value)


def part_verdict(test: str, excess: float, significant: bool) -> str:
    """A part's verdict from which side of its null A - B lies (``excess`` = A - B - null) and whether the
    two-sided test rejects the null: on the claim's side *supported*, on the other *contradicted*;
    otherwise *inconclusive*, or *not shown* for a margin test."""
    if not significant or excess == 0:
        return NOT_SHOWN if test in MARGIN_TESTS else INCONCLUSIVE
    claims_above = test in ("greater", "not_less")
    return SUPPORTED if (excess > 0) == claims_above else CONTRADICTED


def combine(verdicts: Sequence[str]) -> str:
    """A claim's verdict from its parts': contradicted > not run > too few seeds > inconclusive > not shown >
    supported."""
    if not verdicts:
        return NOT_RUN
    for v in (CONTRADICTED, NOT_RUN, TOO_FEW, INCONCLUSIVE, NOT_SHOWN):
        if v in verdicts:
            return v
    return SUPPORTED


def _excludes(e: Estimate, null: float) -> bool:
    return e.lo is not None and e.hi is not None and (e.lo > null or e.hi < null)


def _pct_change(r: float | None) -> float | None:
    return None if r is None or (isinstance(r, float) and math.isnan(r)) else round(100.0 * (r - 1.0), 1)


def judge(an: Analysis, claims: Sequence[Claim], paper: Mapping[str, Sequence[float]],
          labels: Mapping[str, str], margin: float | None = None) -> list[dict[str, Any]]:
    """Every claim with each part's measured difference (t-interval over seeds, within one CPU kind where
    both rows have the seeds there: ``analysis.pair_cells``), its two-sided p-value against the part's null
    (``Part.null``: 0, or ``margin`` points for a margin test; the conf's ``equivalence_margin`` when not
    given), the Holm-adjusted p-value over the family of every claim's parts (fixed in advance: a part
    without a verdict counts as p = 1), the paper's difference, the episode bootstrap's interval
    (secondary) and the verdicts, uncorrected and Holm."""
    margin = default_margin() if margin is None else check_margin(margin)
    out, tested = [], {}
    sizes = holm_families([{"family": c.family, "parts": c.parts} for c in claims])
    for claim in claims:
        parts = []
        for p in claim.parts:
            rec = _measure(an, p, paper, labels, margin, sizes[claim.family])
            if "excess" in rec:
                tested.setdefault(claim.family, []).append(rec)
            parts.append(rec)
        out.append({"id": claim.id, "claim": claim.text, "quote": claim.quote, "source": claim.source,
                    "parts": parts, **({"family": claim.family} if claim.family != MAIN_FAMILY else {})})
    # each family is fixed in advance: every part of its claims, tested or not (``holm``'s family_size)
    for fam, recs in tested.items():
        adjusted, reject = holm([r["p"] for r in recs], family_size=sizes[fam])
        for rec, padj, rej in zip(recs, adjusted, reject):
            rec["p_holm"] = padj
            rec["verdict_holm"] = part_verdict(rec["claim"], rec.pop("excess"), rej)
    for c in out:
        c["verdict"] = combine([p["verdict"] for p in c["parts"]])
        c["verdict_holm"] = combine([p["verdict_holm"] for p in c["parts"]])
    return out


def _measure(an: Analysis, p: Part, paper: Mapping[str, Sequence[float]], labels: Mapping[str, str],
             margin: float, family_size: int = 1) -> dict[str, Any]:
    """One part's record: its difference, p-value, method and uncorrected verdict (``excess``, A - B -
    null unrounded, is kept for the Holm verdict while the part is in the family), and how A and B compare
    in words: ``word`` on the interval corrected by Bonferroni over the ``family_size`` parts of its family,
    ``word_uncorrected`` on the 95% one."""
    null = p.null(margin)
    rec: dict[str, Any] = {"comparison": p.text(labels, margin), "claim": p.test, "test": "two-sided",
                           "null": null, "on": p.on, "paper": p.paper(paper)}
    if p.relative:
        rec["relative"] = {"paper": _pct_change(None if p.paper_relative(paper) is None
                                                else 1.0 + p.paper_relative(paper))}
    if p.a not in an.rows or p.b not in an.rows:
        rec.update(verdict=NOT_RUN, verdict_holm=NOT_RUN, method="–")
        return rec
    pair = an.pair(p.a, p.b)
    cells = {p.b: pair.b, p.a: pair.a}
    va, vb = p.values(cells, p.a), p.values(cells, p.b)
    d = difference(va, {s: p.b_scale * v for s, v in vb.items()}, null=null)
    terms = part_terms(cells, p)
    level = family_level(family_size)
    dc = difference(va, {s: p.b_scale * v for s, v in vb.items()}, level=level)
    if terms:  # the episodes' floor, as ``analysis.row_estimate`` has for a row
        d = with_episode_floor(d, terms, null=null)
        dc = with_episode_floor(dc, terms, level=level)
    note = pair.note()
    means = [float(np.mean(list(va.values()))), p.b_scale * float(np.mean(list(vb.values())))]
    rec.update(measured=d.estimate.as_dict(), p=d.p, method=d.method + (f", {note}" if note else ""),
               seeds=list(d.n), cpu=_cpu(pair), means=means,
               word=word_record(dc, margin, level, f"Bonferroni over the {family_size} parts of its family"),
               word_uncorrected=word(d.estimate.lo, d.estimate.hi, margin) if d.enough_seeds else None)
    if len(pair.kinds) > 1:
        rec["cpus"] = {k: list(n) for k, n in pair.kinds.items()}
    rec["bootstrap"] = _boot_part(an, p, cells).as_dict()
    if p.relative:
        r, lo, hi = ratio_interval([va[s] for s in sorted(va)], [vb[s] for s in sorted(vb)], d.paired)
        method, sides = "Fieller", ratio_terms(cells, p)
        if sides:  # the episodes' floor, as the difference has
            lo, hi, moved = with_ratio_floor(lo, hi, *sides)
            method += ", widened to the episodes' interval" if moved else ""
        rec["relative"].update(mean=_pct_change(r), lo=_pct_change(lo), hi=_pct_change(hi), method=method)
    if not d.enough_seeds:
        rec.update(verdict=TOO_FEW, verdict_holm=TOO_FEW)
    else:
        rec["verdict"] = part_verdict(p.test, d.estimate.mean - null, _excludes(d.estimate, null))
        rec["excess"] = d.estimate.mean - null
    return rec


def _cpu(pair: Pairing) -> str:
    """results.json's ``cpu`` of a comparison: the one kind its cells ran on, or "mixed"."""
    return "mixed" if pair.mixed else str(pair.cpu)


def part_terms(cells: Mapping[str, Sequence[CellResult]], p: Part) -> list[tuple[float, int, int]] | None:
    """A part as a contrast of its rows' pooled episodes (``cells``: each row's cells the comparison uses),
    for the episodes' floor (``cells.episode_terms``): A - b_scale x B on its selector, or that on ``hard``
    minus that on ``easy`` (a scaled B is the same linear contrast with coefficient -b_scale)."""
    sides = [(p.hard, 1.0), (p.easy, -1.0)] if p.on == "gap" else [(p.on, 1.0)]
    return episode_terms(cells, [(sign * side, row, on) for on, sign in sides
                                 for row, side in ((p.a, 1.0), (p.b, -p.b_scale))])


def ratio_terms(cells: Mapping[str, Sequence[CellResult]], p: Part) -> tuple[list, list] | None:
    """A relative part's A and B each as its own terms of pooled episodes on the part's selector, for the
    ratio's episodes' floor (``seed_stats.with_ratio_floor``); None for a gap or a column with no episode."""
    if p.on == "gap":
        return None
    sides = [episode_terms(cells, [(1.0, row, p.on)]) for row in (p.a, p.b)]
    return (sides[0], sides[1]) if all(sides) else None


def _boot_part(an: Analysis, p: Part, cells: Mapping[str, Sequence[CellResult]]) -> Estimate:
    """A part's difference in the episode bootstrap's replicates (secondary): the same statistic on
    every replicate of A and B (paired by episode draw, seeds drawn per row), on the cells the comparison
    uses (``cells``)."""
    ra, rb = an.replicates_of(p.a, cells[p.a]), an.replicates_of(p.b, cells[p.b])
    if p.on == "gap":
        d = ((boot_value(ra, p.hard) - p.b_scale * boot_value(rb, p.hard))
             - (boot_value(ra, p.easy) - p.b_scale * boot_value(rb, p.easy)))
    else:
        d = boot_value(ra, p.on) - p.b_scale * boot_value(rb, p.on)
    va, vb = p.values(cells, p.a), p.values(cells, p.b)
    mean = float(np.mean(list(va.values())) - p.b_scale * np.mean(list(vb.values())))
    return Estimate(mean, *percentile_interval(d))
