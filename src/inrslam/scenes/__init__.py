"""Built-in procedural indoor scenes rendered into RGB-D sequences with ground truth (no download)."""
