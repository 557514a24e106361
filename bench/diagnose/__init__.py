"""Discrepancy workflow: find where the model and the data disagree, name the missing effect (:mod:`.workflow`)."""
