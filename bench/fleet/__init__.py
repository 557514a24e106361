"""servobench fleet: re-identify many logs on Dask distributed and track each axis over time."""
