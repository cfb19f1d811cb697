"""Running jobs in this process or on Dask distributed (:mod:`.executor`, :mod:`.preload`)."""

from .executor import PRELOAD, SCHEDULER_ENV, DaskExecutor, Embedded, Executor, open_executor, run_id

__all__ = ["PRELOAD", "SCHEDULER_ENV", "DaskExecutor", "Embedded", "Executor", "open_executor", "run_id"]
