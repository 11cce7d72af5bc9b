"""Scores of generated scenes: ground truth against the procedural asset (``gt``)."""
