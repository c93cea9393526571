"""The papers yauyau implements, in one table, and how to cite them in user-facing text.

Code comments tag equations by paper number (``# seed 002 (5.35)``: the copies in the project's
seeds folder); everything a user reads names the paper instead, through :func:`cite` (short:
"Yau & Lai (2003), Theorem 3.1") or :func:`cite_full` (authors, title, venue, year).  docs/papers.md
says what each module takes from each paper.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Paper:
    title: str
    authors: tuple[str, ...]
    venue: str | None  # None: not printed in our copy and not confirmed elsewhere
    year: int | None
    doi: str | None  # None: no DOI printed in the paper and none confirmed

    @property
    def short(self) -> str:
        """"Yau & Lai (2003)", "Yau, Du & Jia", "Shi et al. (2017)" (four authors or more: et al.)."""
        surnames = [name.split()[-1] for name in self.authors]
        who = (", ".join(surnames[:-1]) + " & " + surnames[-1]) if 1 < len(surnames) <= 3 else (
            surnames[0] if len(surnames) == 1 else f"{surnames[0]} et al.")
        return f"{who} ({self.year})" if self.year else who

    def to_dict(self) -> dict[str, Any]:
        return {"title": self.title, "authors": list(self.authors), "venue": self.venue, "year": self.year,
                "doi": self.doi, "cite_as": self.short}


PAPERS: dict[str, Paper] = {
    "000": Paper(
        title="Explicit Solution of DMZ Equation in Nonlinear Filtering via Solution of ODEs",
        authors=("Stephen S.-T. Yau", "Yuen-Tai Lai"),
        venue="IEEE Transactions on Automatic Control", year=2003, doi="10.1109/TAC.2003.809169"),
    "001": Paper(
        title="Filtering Problem with Nonlinear Observations and Drift Terms Equal to Gradient Vector "
              "Field plus Affine Vector Field",
        authors=("Stephen S.-T. Yau", "Lixing Jia"),
        venue="Joint IEEE Conference on Decision and Control and European Control Conference "
              "(CDC-ECC), Seville, Spain",
        year=2005, doi=None),
    "002": Paper(
        title="New Algorithms in Real Time Solution of the Nonlinear Filtering Problem",
        authors=("Stephen S.-T. Yau",),
        venue="Communications in Information and Systems, vol. 8, no. 3, pp. 303-332", year=2008, doi=None),
    "003": Paper(
        title="Special Solutions to Some Kolmogorov Equations Arising from Cubic Sensor Problems",
        authors=("Stephen S.-T. Yau", "Ruxu Du", "Lixing Jia"),
        venue=None, year=None, doi=None),
    "004": Paper(
        title="New Classes of Finite Dimensional Filters With Non-Maximal Rank",
        authors=("Ji Shi", "Xiuqiong Chen", "Wenhui Dong", "Stephen S.-T. Yau"),
        venue="IEEE Control Systems Letters", year=2017, doi="10.1109/LCSYS.2017.2713604"),
}


def cite(key: str, where: str = "") -> str:
    """Short citation: cite("000", "Theorem 3.1") -> "Yau & Lai (2003), Theorem 3.1"."""
    short = PAPERS[key].short
    return f"{short}, {where}" if where else short


def cite_full(key: str, where: str = "") -> str:
    """Authors, 'title', venue, year[, where]: the citation a report prints once per paper."""
    paper = PAPERS[key]
    authors = paper.authors[0] if len(paper.authors) == 1 else (
        ", ".join(paper.authors[:-1]) + " and " + paper.authors[-1])
    parts = [authors, f"'{paper.title}'"]
    parts += [str(p) for p in (paper.venue, paper.year) if p]
    if where:
        parts.append(where)
    return ", ".join(parts)


def reference(key: str) -> dict[str, Any]:
    """The JSON form of one paper: title, authors, venue, year, doi (None when not known)."""
    return PAPERS[key].to_dict()
