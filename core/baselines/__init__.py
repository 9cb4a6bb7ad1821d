"""Geometric baselines the learned modules are compared against (no weights)."""
