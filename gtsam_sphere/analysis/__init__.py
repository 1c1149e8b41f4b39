"""Layer 3, analysis: accuracy against check points, uncertainty, comparisons."""
