"""Speaking ROS 2 without ROS 2: ``cdr`` serialises the message types fleetslam publishes,
``node`` is a node made of plain Zenoh exactly as rmw_zenoh makes one (keys, liveliness
tokens, attachments, transient local). What a robot publishes is edge/ros2_out.py."""
