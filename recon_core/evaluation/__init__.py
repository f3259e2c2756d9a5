"""Scoring a DSM against a reference, error maps, colour maps; truth-based checks for synthetic sites."""
