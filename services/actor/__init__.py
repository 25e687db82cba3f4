"""The actor service (see service.py)."""
