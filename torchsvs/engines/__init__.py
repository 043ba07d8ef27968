"""Track datasets beyond one machine: every part of a dataset (a Spark partition or group, a Dask
partition) estimated with one :class:`~torchsvs.track_plan.TrackPlan` settled once on a sample,
by :func:`~torchsvs.track_table.track_table`, so the estimates are those of one process.

- :mod:`torchsvs.engines.spark`: :func:`~torchsvs.engines.spark.track_spark` on a Spark
  DataFrame (``pip install "torchsvs[spark]"``).
- :mod:`torchsvs.engines.dask`: :func:`~torchsvs.engines.dask.track_dask` on a Dask DataFrame
  (``pip install "torchsvs[dask]"``).

Neither Spark nor Dask is imported until one of those modules is.
"""
