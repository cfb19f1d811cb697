"""Reports: HTML + Markdown + metrics.json with PNG images and signed error heat maps.

>>> from shadowlab.report import build, summary_table   # build(out_dir, run) -> index.html path
"""

from .html import build, summary_table

__all__ = ["build", "summary_table"]
