"""Evaluation across methods: side-by-side runs (compare) and the region of attraction (roa)."""
