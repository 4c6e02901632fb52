"""Synthetic dual-iPhone capture studio with ground truth."""
