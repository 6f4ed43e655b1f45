"""Offline tools: bag replay, point files, evaluation against labels, plots and the CLI."""
