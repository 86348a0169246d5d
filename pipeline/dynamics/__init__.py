"""The learned forward-dynamics model (``model``), its training (``training``), its figures."""
