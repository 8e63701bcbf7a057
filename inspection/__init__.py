"""Inspection against CAD: registration, segmentation, form evaluation, reports."""
