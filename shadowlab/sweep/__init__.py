"""Parameter sweeps: every metric of one technique against one of its parameters, per scene
(``shadowlab sweep``), with the points run in this process or on Dask workers [Dask 2024].

* :mod:`.points`: ``NAME=LO:HI:N`` against the technique's Param table; a point as a picklable job
  (:class:`SweepPoint`) and :func:`evaluate_point`, which runs wherever the job does;
* :mod:`.run`: :func:`sweep`, every job checked before any runs;
* :mod:`.report`: sweep.json, summary.md, index.html (a chart per metric per scene).
"""

from .points import ParamRange, SweepPoint, evaluate_point, parse_range
from .report import summary_markdown
from .run import best_points, default_out, results_only, sweep, sweep_jobs

__all__ = ["ParamRange", "SweepPoint", "evaluate_point", "parse_range", "summary_markdown", "best_points",
           "default_out", "results_only", "sweep", "sweep_jobs"]
