"""The services of srl (actor, critic, plant_sim, robot_bridge) and the ``srl`` command."""
