"""The robot_bridge service (see service.py)."""
