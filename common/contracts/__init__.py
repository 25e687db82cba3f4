"""What crosses a process boundary: every key expression (keys), the wire schemas (messages),
run and fleet summaries, and the ROS 2 wire over Zenoh (ros_wire).

Imports ``common`` only from contracts/ and the floors below (math/, system/).
"""
