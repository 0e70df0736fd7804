"""The shape analysis (placeholder docstring, rewritten below)."""
