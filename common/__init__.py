"""Pure building blocks of stacked RL-QV: dynamics, costs, critics, the actor, settings.

The math (dynamics, features, critic, actor, loop) and the contracts (settings, messages,
keys) never import zenoh or ROS; ``common.net.transport`` is the one module that imports zenoh
(tests assert both).
"""
