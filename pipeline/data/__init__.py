"""Data: table schemas, importers of recordings, alignment, training windows, raw streams."""
