"""A paper's qualitative claim, checked on our numbers and said in one plain sentence.

Each comparison states what the paper says, which cells of its results it compares (with the
numbers), and whether the claim holds on this run; ``summary.json`` keeps the three fields per
claim and the comparison prints :meth:`Claim.sentence`, so that a reader needs neither the paper
nor the code to see what was checked.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Claim:
    """``says``: the claim in the paper's words (or ours, marked so); ``compared``: the cells and
    their numbers; ``holds``: whether our numbers bear it out."""

    name: str
    says: str
    compared: str
    holds: bool

    @classmethod
    def from_dict(cls, name: str, entry: dict) -> "Claim":
        """The claim of a summary entry holding ``says``, ``compared`` and ``holds``."""
        return cls(name, entry["says"], entry["compared"], bool(entry["holds"]))

    def as_dict(self) -> dict:
        return {"says": self.says, "compared": self.compared, "holds": bool(self.holds)}

    def sentence(self) -> str:
        return f"{'HOLDS' if self.holds else 'DOES NOT HOLD'}: {self.says} — {self.compared}."


def as_summary(claims: list[Claim]) -> dict:
    """{name: {says, compared, holds}} for summary.json."""
    return {claim.name: claim.as_dict() for claim in claims}


def print_claims(claims: list[Claim], indent: str = "  ", stream=None) -> None:
    """One sentence per claim."""
    for claim in claims:
        print(indent + claim.sentence(), file=stream)
