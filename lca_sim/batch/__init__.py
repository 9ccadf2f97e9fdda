"""Sweeps: a spec's points, built and checked, run on Dask into a Parquet store (docs/sweeps.md)."""
