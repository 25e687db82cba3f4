"""Pure building blocks of stacked RL-QV: dynamics, costs, critics, the actor, settings.

Nothing in this package imports zenoh or ROS (a test asserts it): the services wrap it.
"""
