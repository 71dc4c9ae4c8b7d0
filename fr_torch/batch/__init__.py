"""``fr batch``: many images into a resumable Parquet dataset, in local processes or on Ray."""
