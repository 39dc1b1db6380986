"""Many sequences at once on Ray (trianflow-vo batch)."""
