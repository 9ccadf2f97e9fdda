# Environment for everything in lca_hil that may start ROS 2: DDS stays on loopback, and the
# domain id is ours unless the caller already chose one. Source it; do not run it.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-57}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
