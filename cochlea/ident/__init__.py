"""Identification of the robots' dynamic parameters from their logs (issue 14)."""
