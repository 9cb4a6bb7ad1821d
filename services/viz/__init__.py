"""Views of datasets and results: PNG plots (matplotlib, Agg canvas; never a GUI backend) and Rerun
recordings (`rerun_*.py`; rerun-sdk is the optional `[viz]` extra, imported only when asked for)."""
