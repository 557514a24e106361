"""Streaming excitation runs to a drive and logging them as the samples arrive."""
