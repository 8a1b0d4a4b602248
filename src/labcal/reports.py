"""Markdown reports with plots."""
