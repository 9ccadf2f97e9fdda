"""lca_control.ros."""
