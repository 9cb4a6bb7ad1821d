"""Evaluation reports: one directory per evaluation with report.md, metrics.json and PNG plots."""

from services.reports.writer import Report

__all__ = ["Report"]
