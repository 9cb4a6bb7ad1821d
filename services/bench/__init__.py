"""`n3dmap bench paper`: the paper's experiments end to end on the synthetic world (see paper.py)."""
