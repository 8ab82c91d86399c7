"""Worked examples built with ocpar's public API only: the papers' problems and new ones."""
