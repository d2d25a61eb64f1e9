"""Fleet re-estimation: recorded logs decoded in bulk and estimated in parallel on Dask.

The data path of one drive: log file -> :mod:`.decode` (frames grouped by id,
signals decoded with vectorised bit extraction from the service's DBC and
mapping) -> :class:`.samples.SampleArrays` (the service's 1 s samples, as
arrays) -> the vectorised estimator -> per-drive Parquet.  :mod:`.batch` runs
drives (or vehicles, chained) as Dask tasks.
"""
