"""The correction strategies by name (``--strategy``): an unknown name fails listing the known ones."""

from __future__ import annotations

from ncfix.config import Options
from ncfix.correct.epa_strategy import EpaStrategy
from ncfix.correct.solve import GraphStrategy, Strategy

STRATEGIES = {"graph": GraphStrategy, "epa": EpaStrategy}


def make_strategy(options: Options) -> Strategy:
    """The strategy ``options.strategy`` names, made with these options."""
    try:
        strategy = STRATEGIES[options.strategy]
    except KeyError:
        raise NotImplementedError(f"unknown strategy {options.strategy!r} (known: {', '.join(STRATEGIES)})") from None
    return strategy(options)
