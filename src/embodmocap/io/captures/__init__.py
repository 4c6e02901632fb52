"""Capture readers and writers, one module per phone app format."""
