"""Recordings of predictions in the formats perception tools read: MCAP with Foxglove's schemas
(:mod:`radar.recorders.foxglove_mcap`), MCAP with ROS 2 messages (:mod:`radar.recorders.ros2_mcap`) and Rerun's
``.rrd`` (:mod:`radar.recorders.rerun_rrd`), all written from the same frames (:mod:`radar.recorders.frames`)."""
