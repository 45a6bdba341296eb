"""Benchmark suite: accuracy, robustness and speed of the alignment methods, side by side.

* :mod:`gridmerge.bench.datasets` -- the cases: simulated robot pairs with exact truth
  (tiers of difficulty, negative pairs), the annotated real Halmstad pairs, the paper's
  Table I experiment;
* :mod:`gridmerge.bench.metrics` -- scoring one result (success, precise, declined, wrong,
  false merge, errors) and summaries;
* :mod:`gridmerge.bench.runner` -- :func:`run` every method on every case into a results
  folder, :class:`BenchRun`, :func:`compare`.

From the command line: ``gridmerge bench [run] ...`` and ``gridmerge bench compare RUN1 RUN2``.
"""

from .datasets import Case, Dataset, halmstad, paper, simulated
from .metrics import Record, evaluate, summarize
from .runner import BenchRun, compare, run

__all__ = [
    "Case",
    "Dataset",
    "simulated",
    "halmstad",
    "paper",
    "Record",
    "evaluate",
    "summarize",
    "BenchRun",
    "run",
    "compare",
]
