"""Scoring and the HTML report: metrics, scoring against ground truth, figures, overlays, pages."""
