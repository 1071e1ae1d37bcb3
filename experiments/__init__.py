"""Experiments over many runs: resumable sweeps, learning-curve plots and result tables."""
