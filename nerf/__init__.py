"""Radiance fields in PyTorch: volume rendering (pure functions), fields, training, rendering."""
