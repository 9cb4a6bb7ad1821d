"""Plots of datasets and results (matplotlib, Agg canvas; never a GUI backend)."""
