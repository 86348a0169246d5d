"""The arm over ROS 2: ``collect`` with ``robot=ros2``, the digital twin (``stage=twin``), bags.

- ``collector.py``: the collect node (commands out at ``control_hz``, poses in, watchdog,
  safe stop) and :func:`~pipeline.ros2.collector.collect_ros2`, which records the tables the
  ``collect`` stage writes into its artifact.
- ``twin.py``: the simulated arm (``pipeline/arm/sim_arm.py``) as a ROS 2 node.
- ``node.py`` (rclpy, its context, QoS, signals), ``gate.py`` (the safety gate of outgoing commands), ``recorder.py`` (Parquet chunks).

rclpy comes from the optional ``ros`` extra; this package imports it only when a node is made,
so that without it ``robot=ros2`` and ``stage=twin`` fail with one line saying how to install it.
"""
