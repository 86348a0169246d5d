"""Data: table schemas, importers of recordings, alignment, runs as records, training windows,
raw streams."""
