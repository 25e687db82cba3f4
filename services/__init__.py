"""The processes of srl, one folder each (actor, critic, plant_sim, robot_bridge, tb3_emulator): thin
adapters over common/; the ``srl`` command that starts them is in tools/ (docs/architecture.md)."""
