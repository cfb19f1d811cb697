"""``shadowlab bench``: speed, measured in one run (never asserted in tests).

* :mod:`.core` — ground truth, techniques, filtered shadow maps, parameter sweeps, fitting
  (``reports/bench/bench.json`` and ``bench.md``); :func:`run` runs them all;
* :mod:`.sdf` — the SDF soft-shadow benchmarks (``sdf.json`` / ``sdf.md``, ``--only sdf``);
* :mod:`.cascades` — cascaded shadow maps: cost beside the source's FPS table, quality at equal
  texels, error against texels, shimmer (``cascades.json`` / ``cascades.md``, ``--only cascades``);
* :mod:`.timing` — :func:`timed`, the one timing helper every benchmark uses.
"""

from .core import run
from .timing import timed, warm_median

__all__ = ["run", "timed", "warm_median"]
