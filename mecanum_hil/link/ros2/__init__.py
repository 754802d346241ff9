"""ROS 2 over DDS, with no ROS install: mecanum-hil as a ROS 2 node.

ROS 2 speaks DDS-RTPS on the wire. A DDS participant that follows ROS 2's naming (topic
``rt/<name>``, type ``<pkg>::msg::dds_::<Type>_``) and the message layouts of the interface
definitions is a ROS 2 node to every other node, whatever middleware they run. This package
does that with Cyclone DDS's Python binding (the ``ros2`` extra):

- :mod:`.messages`: the message types, field by field;
- :mod:`.convert`: pure conversions between ROS messages and the three commands, wheel rpm
  and the pose (the exact inverse of ``import``'s);
- :mod:`.node`: the participant, topic names, the domain and the QoS profiles;
- :mod:`.transport`: the ``ros2`` transport of ``record`` (cmd_vel out, joint_states and
  odom in);
- :mod:`.sim_robot`: a simulated ROS 2 Mecanum robot (``sim-robot --transport ros2``).

A passive ``shadow`` hears a ROS 2 robot through ``monitor/ros2_listen.py``. Nothing here is
imported by the core install: each module imports ``cyclonedds`` itself.
"""
