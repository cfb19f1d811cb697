"""``shadowlab bench``: speed, measured in one run (never asserted in tests).

* :mod:`.core` — ground truth, techniques, filtered shadow maps, parameter sweeps, fitting
  (``reports/bench/bench.json`` and ``bench.md``); :func:`run` runs them all;
* :mod:`.sdf` — the SDF soft-shadow benchmarks (``sdf.json`` / ``sdf.md``, ``--only sdf``);
* :mod:`.cascades` — cascaded shadow maps: cost beside the source's FPS table, quality at equal
  texels, error against texels, shimmer (``cascades.json`` / ``cascades.md``, ``--only cascades``);
* :mod:`.frames` — every technique's new and warm frame, split into G-buffer, light views,
  technique and host time, with its kernels and first host synchronisation, beside raw
  ``ray_test`` (``frames.json`` / ``frames.md``, ``--only frames``, not in the full run);
* :mod:`.rays` — raw Mitsuba ``ray_test`` in one wavefront, the ceiling rays are measured against;
* :mod:`.claims` — the sources' speed figures beside the latest run records' (a table of the
  docs' bench page);
* :mod:`.timing` — :func:`timed`, the one timing helper every benchmark uses.
"""

from .core import run
from .timing import timed, warm_median

__all__ = ["run", "timed", "warm_median"]
