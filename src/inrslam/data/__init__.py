"""Datasets: one protocol (`RGBDDataset`) yielding `Frame`s; readers per public layout."""
