"""File formats and atomic writing (kept apart from the maths)."""
