"""The plant_sim service (see service.py)."""
