"""Infrastructure: the artifact store, Parquet and atomic writes, experiment tracking."""
