"""Live nodes over eclipse-zenoh, speaking ROS 2 CDR as zenoh-bridge-ros2dds forwards it.

``session`` (configs: explicit endpoints, no scouting), ``codec`` (CDR payloads), ``markers``
(RViz markers), ``stats`` and ``node``
(the zenoh driver), and the nodes: ``relocalize`` (D and phi, paper §3.2.2), ``replay``
(recorded poses or bag topics), ``localize`` (world_T_cam from detections or images); ``cli`` is
``tagtrail stream``.
"""
