"""What the user reads: terminal summaries, plots, diagnose and commissioning reports."""
