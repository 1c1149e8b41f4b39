"""Layer 2, estimation: factors, solvers, initialisation, kNN corrections,
calibration runs, rigs."""
