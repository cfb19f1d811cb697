"""Reports: HTML + Markdown + metrics.json with PNG images and signed error heat maps.

A comparison's result is a typed :class:`~shadowlab.report.run.Run` (``run.py``); ``html.py``
writes its page, ``tables.py`` its tables and summary.md, ``panels.py`` the HTML pieces and a
family's panel rows, ``jsonable.py`` metrics.json.

>>> from shadowlab.report import build, summary_table   # build(out_dir, run) -> index.html path
"""

from .html import build
from .run import Reference, Run, RunImages, Images, TechniqueRun
from .tables import summary_table

__all__ = ["build", "summary_table", "Run", "Reference", "TechniqueRun", "Images", "RunImages"]
