"""Layer 1, formats and files: the dataset and calibration contracts (../shared/spec/dataset.md)."""
