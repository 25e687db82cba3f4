"""The emulated TurtleBot3 Burger (see service.py)."""
