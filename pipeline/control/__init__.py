"""A trained policy driving the arm (``stage=control``): on ROS 2 in real time, or on the
in-process simulated arm in simulated time, through one loop (:mod:`pipeline.control.loop`)."""
