"""Mitsuba 3 dataset generation: cameras, rendering, dataset files. Only place that imports mitsuba."""
