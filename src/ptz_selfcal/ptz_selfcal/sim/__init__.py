"""Simulation and evaluation: rendering, synthetic data, metrics (not used by the nodes)."""
