"""lca_sim.ros."""
