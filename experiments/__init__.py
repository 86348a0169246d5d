"""Measurement scripts, run from the checkout with ``python -m experiments.<name>``."""
