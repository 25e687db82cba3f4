"""The critic service (see service.py)."""
