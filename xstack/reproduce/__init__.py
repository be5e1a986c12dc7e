"""Reproduce the paper's Table 2 end to end (Lindroos et al. 2015, §4–5).

:func:`~xstack.reproduce.run.reproduce` runs the paper's whole procedure for a data-set type
over Monte Carlo realisations with the public API (simulate → image/CLEAN → subtract →
uv-stack and image-stack → fits → analytic noise) and compares with the paper's row
(:mod:`xstack.reproduce.paper`). This is the last stage: it may import every other stage and
nothing but the command line imports it.
"""

from xstack.reproduce.paper import PAPER_TABLE2, PROCEDURES, paper_row
from xstack.reproduce.run import ReproduceResult, reproduce

__all__ = ["PAPER_TABLE2", "PROCEDURES", "ReproduceResult", "paper_row", "reproduce"]
