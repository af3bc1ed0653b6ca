"""ROS 2's wire as rmw_zenoh speaks it, for mfvs to publish on the same zenoh network (docs/ros2.md).

keys: data keys and liveliness tokens; attachment: the per-sample attachment; cdr: the CDR codec of the types
mfvs uses; types: their ROS names and type hashes; gid: the GIDs rmw_zenoh derives from tokens. Pure: no zenoh,
no ROS 2 installation.
"""
