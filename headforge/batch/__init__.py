"""Jobs over many inputs with per-item isolation and resume; Ray as an optional backend.

See :mod:`headforge.batch.runner`. Used by ``headforge craft register`` (HeadCraft's
registration of a folder of scans) and meant for tracking/fitting many inputs as well.
"""

from headforge.batch.runner import BatchResult, ItemResult, run_batch, summary_table

__all__ = ["BatchResult", "ItemResult", "run_batch", "summary_table"]
