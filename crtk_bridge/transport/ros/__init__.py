"""The ROS 2 graph over Zenoh, in rmw_zenoh's format (front process only; never imported by the
control process): ``types`` (the one rosbags type store, CDR, RIHS01 hashes), ``rmw`` (key
expressions, liveliness tokens, attachments, QoS text, publishers and subscriptions) and ``graph``
(every namespace's CRTK topics, ``/joint_states``, ``/tf``, ``/robot_description``, commands
through the server's session path)."""
