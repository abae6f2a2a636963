"""Evaluation against ground truth: metrics and plots."""
