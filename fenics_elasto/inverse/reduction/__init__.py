"""Reduced force bases: PCA of example wall motions, training with and without scans."""
